"""State estimate from the HIL sensors: what the stub's controller believes.

Two sources, chosen once at construction:
- sensors (default): a Mahony-style complementary attitude filter (gyro integration corrected
  by the accelerometer's specific-force direction, compensated with the GPS-derived
  acceleration, and by the magnetometer's heading plus the WMM declination) and a fixed-gain
  position/velocity filter per axis (accelerometer prediction, GPS position/velocity and
  barometric height corrections, accelerometer bias states; the baro's zero is tied to GPS
  height). The local NED origin is the first GPS fix, like PX4's EKF origin. Like EKF2, the
  position is reported valid (armable) only after an initial alignment of ALIGN_S (3 s of
  simulated time) with boosted attitude gains. After a reset of a running vehicle (see
  `SensorEstimator.reset`) the alignment is the short WARM_ALIGN_S.
- `ground_truth_estimate=True`: copies SensorFrame.truth (clearly not what PX4 would know;
  faster and noise-free, for RL speed runs).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from sitl_bridge.sensors import GroundTruth
from sitl_bridge.sensors.environment import magnetic_field_ned_gauss, pressure_altitude_m
from sitl_bridge.world.schema import GeoHome

from .vec import (
    Quat,
    Vec3,
    quat_from_euler,
    quat_multiply,
    quat_normalize,
    quat_rotate,
    quat_rotate_inverse,
    quat_to_euler,
    wrap_pi,
)

if TYPE_CHECKING:
    from sitl_bridge.sensors import SensorFrame

GRAVITY_M_S2 = 9.80665
EARTH_RADIUS_M = 6378137.0


@dataclass
class Estimate:
    """The vehicle state as the autopilot sees it (NED / FRD, SI units)."""

    time_us: int = 0
    position_ned_m: Vec3 = (0.0, 0.0, 0.0)          # relative to `origin`
    velocity_ned_m_s: Vec3 = (0.0, 0.0, 0.0)
    accel_ned_m_s2: Vec3 = (0.0, 0.0, 0.0)          # kinematic, gravity removed
    quaternion_ned_frd: Quat = (1.0, 0.0, 0.0, 0.0)
    angular_velocity_frd_rad_s: Vec3 = (0.0, 0.0, 0.0)
    lat_deg: float = 0.0
    lon_deg: float = 0.0
    alt_amsl_m: float = 0.0
    # local origin (lat deg, lon deg, alt m AMSL); None until the first GPS fix
    origin: tuple[float, float, float] | None = None
    attitude_valid: bool = False
    position_valid: bool = False
    # last GPS as received (for GPS_RAW_INT)
    gps_fix_type: int = 0
    gps_satellites: int = 0
    gps_eph_cm: int = 9999
    gps_epv_cm: int = 9999

    @property
    def euler_rad(self) -> Vec3:
        """(roll, pitch, yaw) in rad."""
        return quat_to_euler(self.quaternion_ned_frd)


#: Truth placeholder of frames decoded before any ground truth arrived (HIL path).
NO_TRUTH = GroundTruth(
    quaternion_ned_frd=np.array((1.0, 0.0, 0.0, 0.0)), angular_velocity_frd_rad_s=np.zeros(3),
    lat_e7=0, lon_e7=0, alt_mm=0, velocity_ned_m_s=np.zeros(3), accel_ned_m_s2=np.zeros(3),
    position_ned_m=np.zeros(3),
)


def _floats(v) -> tuple[float, ...] | list[float]:
    """Python floats of a 3-vector (numpy arrays index slowly element by element). Tuples (the
    stub's HIL client decodes into them) pass as they are."""
    if type(v) is tuple:
        return v
    try:
        return v.tolist()
    except AttributeError:
        return [float(x) for x in v]


class GroundTruthEstimator:
    """Estimate = SensorFrame.truth. Labelled as such: PX4 never sees ground truth."""

    def __init__(self) -> None:
        self.estimate = Estimate()
        self._origin_ned: Vec3 | None = None
        self._m_per_deg = (1.0, 1.0)   # metres per degree of latitude, longitude at the origin

    def reset(self) -> None:
        """Forget everything: the next frame's truth is the new origin."""
        self.estimate = Estimate()
        self._origin_ned = None

    def update(self, frame: SensorFrame) -> Estimate:
        """Copy the truth of this frame into the estimate."""
        t = frame.truth
        e = self.estimate
        if t is NO_TRUTH:
            e.time_us = frame.time_us
            return e
        # `raw`: the truth as plain-float tuples (quaternion, rates, velocity, accel, position);
        # the numpy views would cost more to build than this whole update
        q, rates, vel, acc, (px, py, pz) = t.raw
        if self._origin_ned is None:
            self._origin_ned = (px, py, pz)
            e.origin = (t.lat_e7 * 1e-7, t.lon_e7 * 1e-7, t.alt_mm * 1e-3)  # geodetic only once
            self._m_per_deg = (math.radians(EARTH_RADIUS_M),
                               math.radians(EARTH_RADIUS_M * math.cos(math.radians(e.origin[0]))))
        o = self._origin_ned
        e.time_us = frame.time_us
        north, east, down = px - o[0], py - o[1], pz - o[2]
        e.position_ned_m = (north, east, down)
        e.velocity_ned_m_s = vel
        e.accel_ned_m_s2 = acc
        e.quaternion_ned_frd = q
        e.angular_velocity_frd_rad_s = rates
        # geodetic position from the local one around the origin, as `SensorEstimator` does
        # (cm-exact over an env's workspace; a projection per step would cost more)
        lat0, lon0, alt0 = e.origin  # type: ignore[misc]
        m_lat, m_lon = self._m_per_deg
        e.lat_deg = lat0 + north / m_lat
        e.lon_deg = lon0 + east / m_lon
        e.alt_amsl_m = alt0 - down
        e.attitude_valid = True
        e.position_valid = True
        gps = frame.gps
        if gps is not None:
            e.gps_fix_type, e.gps_satellites = int(gps.fix_type), int(gps.satellites)
            e.gps_eph_cm, e.gps_epv_cm = int(gps.eph_cm), int(gps.epv_cm)
        elif e.gps_fix_type < 3 or e.gps_satellites < 10 or e.gps_eph_cm > 100 or e.gps_epv_cm > 100:
            # no GPS in this frame: at least a good 3D fix (tested first, it holds after once)
            e.gps_fix_type = max(e.gps_fix_type, 3)
            e.gps_satellites = max(e.gps_satellites, 10)
            e.gps_eph_cm, e.gps_epv_cm = min(e.gps_eph_cm, 100), min(e.gps_epv_cm, 100)
        return e


class SensorEstimator:
    """Complementary attitude filter + GPS/baro/accelerometer position filter."""

    # attitude: proportional / integral correction gains (1/s, 1/s^2)
    ACC_KP = 0.4
    MAG_KP = 0.3
    GYRO_BIAS_KI = 0.01
    ALIGN_S = 3.0                  # fast initial alignment: gains x ALIGN_BOOST for this long
    ALIGN_BOOST = 10.0
    WARM_ALIGN_S = 1.0             # the same after `reset()` (warm sensors; see there)
    # position filter: gains per GPS update for position, velocity, accel bias
    GPS_POS_GAIN = 0.25
    GPS_VEL_GAIN = 0.35
    GPS_POS_TO_VEL = 0.1
    ACC_BIAS_GAIN = 0.02
    BARO_GAIN_PER_S = 2.0          # 1/s pull of the height to the baro height
    BARO_VEL_GAIN_PER_S = 0.5
    BARO_OFFSET_SAMPLES = 25       # GPS samples averaged for the baro-to-GPS height offset,
    BARO_OFFSET_GAIN = 0.01        # then tracked slowly (baro drift)
    MIN_GPS_FIX = 3
    MIN_GPS_SATELLITES = 6

    def __init__(self, align_s: float | None = None) -> None:
        self.align_s = self.ALIGN_S if align_s is None else float(align_s)
        self.estimate = Estimate()
        self._q: Quat | None = None
        self._gyro_bias = [0.0, 0.0, 0.0]
        self._pos = [0.0, 0.0, 0.0]
        self._vel = [0.0, 0.0, 0.0]
        self._acc_bias_ned = [0.0, 0.0, 0.0]
        self._last_time_us: int | None = None
        self._baro_offset_m: float | None = None   # baro altitude - GPS altitude at origin
        self._last_baro_us: int | None = None
        self._last_baro_alt_m: float | None = None
        self._baro_offset_samples = 0
        self._align_until_us: int | None = None
        self._accel_lp: Vec3 = (0.0, 0.0, 0.0)
        # kinematic acceleration from GPS velocity differences: the accelerometer measures
        # gravity minus this, so the tilt correction must not mistake it for a tilt
        self._gps_accel_ned = [0.0, 0.0, 0.0]
        self._last_gps: tuple[int, Vec3] | None = None
        self._declination_rad = 0.0   # known once the origin is: heading = field heading + this
        self._lon_radius_origin: tuple[float, float, float] | None = None
        self._lon_radius_m = EARTH_RADIUS_M

    def reset(self, align_s: float | None = None) -> None:
        """Re-initialise from the next sensor samples, as after a reboot of a running vehicle,
        with an alignment of `align_s` (default WARM_ALIGN_S) instead of the cold ALIGN_S.

        Why shorter: ALIGN_S stands for EKF2's wait after a cold boot. After a reset the IMU,
        magnetometer, barometer and GPS are already running with a 3D fix (the simulated
        sensors have no warm-up of their own), the initial attitude is taken from the first
        accelerometer/magnetometer sample as at boot, and the origin from the first GPS fix
        (<= 0.2 s at 5 Hz). WARM_ALIGN_S = 1 s still spans three time constants of the boosted
        heading loop (1 / (MAG_KP * ALIGN_BOOST) = 0.33 s; the tilt loop's is 0.25 s), which
        removes ~95 % of the single-sample initial error, and five GPS fixes for the position
        and velocity filter. Learnt states (gyro and accelerometer biases, baro offset) start
        over: the vehicle may have moved, and a reset re-draws the sensor noise."""
        self.__init__(self.WARM_ALIGN_S if align_s is None else align_s)  # type: ignore[misc]

    def update(self, frame: SensorFrame) -> Estimate:
        """Fold one SensorFrame into the estimate."""
        time_us = frame.time_us
        dt = 0.0 if self._last_time_us is None else (time_us - self._last_time_us) * 1e-6
        self._last_time_us = time_us
        acc_b = frame.accel_frd_m_s2
        # Python floats: numpy arrays (SensorSuite) index slowly; tuples (HIL client) pass as they are
        acc_b = acc_b if type(acc_b) is tuple else tuple(_floats(acc_b))
        gyro = frame.gyro_frd_rad_s
        gx, gy, gz = gyro if type(gyro) is tuple else _floats(gyro)
        gb = self._gyro_bias
        w = (gx - gb[0], gy - gb[1], gz - gb[2])
        if self._q is None:
            self._q = self._initial_attitude(acc_b, frame.mag_frd_gauss)
        if dt > 0.0:
            self._attitude_step(dt, acc_b, w, frame.mag_frd_gauss, time_us)
        q = self._q
        e = self.estimate
        e.time_us = time_us
        e.quaternion_ned_frd = q
        e.angular_velocity_frd_rad_s = w
        e.attitude_valid = True

        # kinematic acceleration in NED = R f + g
        fn, fe, fd = quat_rotate(q, acc_b)
        ab = self._acc_bias_ned
        an, ae, ad = fn - ab[0], fe - ab[1], fd + GRAVITY_M_S2 - ab[2]
        pos, vel = self._pos, self._vel
        if e.origin is not None and dt > 0.0:
            half_dt = 0.5 * dt
            pos[0] += (vel[0] + an * half_dt) * dt
            pos[1] += (vel[1] + ae * half_dt) * dt
            pos[2] += (vel[2] + ad * half_dt) * dt
            vel[0] += an * dt
            vel[1] += ae * dt
            vel[2] += ad * dt
        lp = self._accel_lp
        self._accel_lp = (lp[0] + 0.2 * (an - lp[0]), lp[1] + 0.2 * (ae - lp[1]), lp[2] + 0.2 * (ad - lp[2]))

        gps = frame.gps
        if gps is not None:
            self._gps_update(e, gps)
        baro = frame.baro
        if baro is not None and e.origin is not None and dt > 0.0:
            # PX4 ignores HIL_SENSOR.pressure_alt: height comes from the pressure itself
            self._baro_update(pressure_altitude_m(baro.pressure_hpa * 100.0), time_us)

        # the GPS update may have replaced the lists
        pos, vel = self._pos, self._vel
        # like EKF2, report a usable position only once the attitude has aligned
        e.position_valid = e.origin is not None and self._align_until_us is not None \
            and time_us >= self._align_until_us
        e.position_ned_m = (pos[0], pos[1], pos[2])
        e.velocity_ned_m_s = (vel[0], vel[1], vel[2])
        e.accel_ned_m_s2 = self._accel_lp
        origin = e.origin
        if origin is not None:
            lat0, lon0, alt0 = origin
            if self._lon_radius_origin is not origin:  # the cosine once per origin, not per step
                self._lon_radius_origin = origin
                self._lon_radius_m = EARTH_RADIUS_M * math.cos(math.radians(lat0))
            e.lat_deg = lat0 + math.degrees(pos[0] / EARTH_RADIUS_M)
            e.lon_deg = lon0 + math.degrees(pos[1] / self._lon_radius_m)
            e.alt_amsl_m = alt0 - pos[2]
        return e

    # --- attitude ----------------------------------------------------------------------
    def _initial_attitude(self, acc_b: Vec3, mag) -> Quat:
        # roll/pitch from gravity; yaw from the magnetometer (heading relative to the field)
        roll = math.atan2(-acc_b[1], -acc_b[2])
        pitch = math.atan2(acc_b[0], math.hypot(acc_b[1], acc_b[2]))
        yaw = 0.0
        if mag is not None:
            q_rp = quat_from_euler(roll, pitch, 0.0)
            m = quat_rotate(q_rp, (float(mag[0]), float(mag[1]), float(mag[2])))
            yaw = -math.atan2(m[1], m[0])
        return quat_from_euler(roll, pitch, yaw)

    def _attitude_step(self, dt: float, acc_b: Vec3, w: Vec3, mag, time_us: int) -> None:
        q = self._q
        cx = cy = cz = 0.0   # attitude correction (body rates)
        if self._align_until_us is None:
            self._align_until_us = time_us + int(self.align_s * 1e6)
        boost = self.ALIGN_BOOST if time_us < self._align_until_us else 1.0
        ax, ay, az = acc_b
        a_norm = math.sqrt(ax * ax + ay * ay + az * az)
        # trust the accelerometer's gravity direction only near 1 g
        ga = self._gps_accel_ned
        rx, ry, rz = ga[0], ga[1], ga[2] - GRAVITY_M_S2   # expected specific force, NED
        ref_norm = math.sqrt(rx * rx + ry * ry + rz * rz)
        if 0.5 * GRAVITY_M_S2 < a_norm < 1.5 * GRAVITY_M_S2 and ref_norm > 1.0:
            mx, my, mz = ax / a_norm, ay / a_norm, az / a_norm  # measured: specific force points up
            ex, ey, ez = quat_rotate_inverse(q, (rx / ref_norm, ry / ref_norm, rz / ref_norm))
            # error = measured x estimated
            k = self.ACC_KP * boost
            cx = k * (my * ez - mz * ey)
            cy = k * (mz * ex - mx * ez)
            cz = k * (mx * ey - my * ex)
        qw, qx, qy, qz = q
        if mag is not None:
            m_ned = quat_rotate(q, _floats(mag))
            # heading error about world down, applied in body frame
            heading_err = wrap_pi(self._declination_rad - math.atan2(m_ned[1], m_ned[0]))
            # world down in the body: quat_rotate_inverse(q, (0, 0, 1)) written out
            k = self.MAG_KP * boost * heading_err
            cx += 2.0 * (qx * qz - qw * qy) * k
            cy += 2.0 * (qy * qz + qw * qx) * k
            cz += (1.0 - 2.0 * (qx * qx + qy * qy)) * k
        gb = self._gyro_bias
        ki = self.GYRO_BIAS_KI
        gb[0] -= ki * cx * dt
        gb[1] -= ki * cy * dt
        gb[2] -= ki * cz * dt
        wx, wy, wz = w[0] + cx, w[1] + cy, w[2] + cz
        h = 0.5 * dt
        # integrate, then quat_normalize written out (w stays positive for small steps; the
        # sign flip keeps quat_normalize's convention when it does not)
        nw = qw + h * (-qx * wx - qy * wy - qz * wz)
        nx = qx + h * (qw * wx + qy * wz - qz * wy)
        ny = qy + h * (qw * wy - qx * wz + qz * wx)
        nz = qz + h * (qw * wz + qx * wy - qy * wx)
        n = math.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
        if nw < 0.0:
            n = -n
        self._q = (nw / n, nx / n, ny / n, nz / n)

    # --- position ----------------------------------------------------------------------
    def _gps_update(self, e: Estimate, gps) -> None:
        e.gps_fix_type, e.gps_satellites = int(gps.fix_type), int(gps.satellites)
        e.gps_eph_cm, e.gps_epv_cm = int(gps.eph_cm), int(gps.epv_cm)
        if gps.fix_type < self.MIN_GPS_FIX or gps.satellites < self.MIN_GPS_SATELLITES:
            return
        lat, lon, alt = gps.lat_e7 * 1e-7, gps.lon_e7 * 1e-7, gps.alt_mm * 1e-3
        vel = (gps.vn_cm_s * 0.01, gps.ve_cm_s * 0.01, gps.vd_cm_s * 0.01)
        if self._last_gps is not None and e.time_us > self._last_gps[0]:
            dt_gps = (e.time_us - self._last_gps[0]) * 1e-6
            prev = self._last_gps[1]
            for k in range(3):
                self._gps_accel_ned[k] += 0.5 * ((vel[k] - prev[k]) / dt_gps - self._gps_accel_ned[k])
        self._last_gps = (e.time_us, vel)
        if e.origin is None:
            e.origin = (lat, lon, alt)
            self._pos = [0.0, 0.0, 0.0]
            self._vel = list(vel)
            # true heading = magnetic heading + declination (PX4 looks it up in the WMM too)
            n, east, _ = magnetic_field_ned_gauss(GeoHome(lat_deg=lat, lon_deg=lon, alt_m=alt))
            self._declination_rad = math.atan2(east, n)
            if self._q is not None:
                half = 0.5 * self._declination_rad
                self._q = quat_normalize(quat_multiply((math.cos(half), 0.0, 0.0, math.sin(half)), self._q))
            return
        lat0, lon0, alt0 = e.origin
        meas = (
            math.radians(lat - lat0) * EARTH_RADIUS_M,
            math.radians(lon - lon0) * EARTH_RADIUS_M * math.cos(math.radians(lat0)),
            alt0 - alt,
        )
        if self._last_baro_alt_m is not None and self._baro_offset_m is not None:
            # the baro's zero is tied to GPS height: averaged at first, then tracked slowly
            n = self._baro_offset_samples = self._baro_offset_samples + 1
            gain = 1.0 / n if n <= self.BARO_OFFSET_SAMPLES else self.BARO_OFFSET_GAIN
            self._baro_offset_m += gain * (self._last_baro_alt_m + meas[2] - self._baro_offset_m)
        # horizontal from GPS; vertical position from baro (PX4 EKF2_HGT_REF=baro), velocity from GPS
        for k in range(3):
            if k < 2 or self._baro_offset_m is None:
                ep = meas[k] - self._pos[k]
                self._pos[k] += self.GPS_POS_GAIN * ep
                self._vel[k] += self.GPS_POS_TO_VEL * ep
            ev = vel[k] - self._vel[k]
            self._vel[k] += self.GPS_VEL_GAIN * ev
            self._acc_bias_ned[k] -= self.ACC_BIAS_GAIN * ev

    def _baro_update(self, pressure_alt_m: float, time_us: int) -> None:
        last = self._last_baro_us
        self._last_baro_us = time_us
        self._last_baro_alt_m = pressure_alt_m
        if self._baro_offset_m is None or last is None:
            self._baro_offset_m = pressure_alt_m + self._pos[2]   # baro alt at local z = 0
            return
        dt = min(max(time_us - last, 0) * 1e-6, 0.5)
        z_baro = self._baro_offset_m - pressure_alt_m
        ez = z_baro - self._pos[2]
        self._pos[2] += min(1.0, self.BARO_GAIN_PER_S * dt) * ez
        self._vel[2] += min(1.0, self.BARO_VEL_GAIN_PER_S * dt) * ez
