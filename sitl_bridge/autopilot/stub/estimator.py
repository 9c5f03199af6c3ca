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

from sitl_bridge import frames
from sitl_bridge.jit import dual, kernel
from sitl_bridge.sensors import GroundTruth
from sitl_bridge.sensors.environment import magnetic_field_ned_gauss, pressure_altitude_m
from sitl_bridge.world.schema import GeoHome

from . import vec
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


# GroundTruthEstimator.state layout: the origin in the truth's NED, metres per degree of
# latitude and longitude there, the origin's (lat deg, lon deg, alt m AMSL)
_GT_ORIGIN_NED, _GT_M_PER_DEG, _GT_ORIGIN = 0, 3, 5
GROUND_TRUTH_STATE = 8


@dual
def relative_estimate(g, q: Quat, rates: Vec3, vel: Vec3, acc: Vec3, px: float, py: float,  # noqa: ANN001
                      pz: float) -> tuple[Quat, Vec3, Vec3, Vec3, Vec3, float, float, float]:
    """The ground-truth estimate around the origin in `g` (`GroundTruthEstimator.state`, as an
    array or a tuple): (attitude, rates, position, velocity, acceleration, lat, lon, alt AMSL).
    The geodetic position comes from the local one around the origin, as `SensorEstimator`
    does (cm-exact over an env's workspace; a projection per step would cost more)."""
    north, east, down = px - g[_GT_ORIGIN_NED], py - g[_GT_ORIGIN_NED + 1], pz - g[_GT_ORIGIN_NED + 2]
    return (q, rates, (north, east, down), vel, acc, g[_GT_ORIGIN] + north / g[_GT_M_PER_DEG],
            g[_GT_ORIGIN + 1] + east / g[_GT_M_PER_DEG + 1], g[_GT_ORIGIN + 2] - down)


class GroundTruthEstimator:
    """Estimate = SensorFrame.truth. Labelled as such: PX4 never sees ground truth.

    The origin lives in the float64 `state` vector (`relative_estimate`, which the fused
    `direct` loop compiles in) once `has_origin`."""

    def __init__(self) -> None:
        self.estimate = Estimate()
        self.state = np.zeros(GROUND_TRUTH_STATE)
        self._origin: tuple[float, ...] = tuple(self.state.tolist())
        self.has_origin = False

    def reset(self) -> None:
        """Forget everything: the next frame's truth is the new origin."""
        self.estimate = Estimate()
        self.has_origin = False

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
        if not self.has_origin:
            self._set_origin(t)
        return self.finish(relative_estimate(self._origin, q, rates, vel, acc, px, py, pz), frame.time_us, frame.gps)

    def place(self, spawn: GroundTruth, placed: GroundTruth, time_us: int) -> Estimate:
        """After `reset`: the estimate as it stands after a take-off from `spawn` (the truth
        there, which the first frame would have made the origin) to `placed` (an episode that
        starts in the air, `StubAutopilot.place_in_air`)."""
        self._set_origin(spawn)
        q, rates, vel, acc, (px, py, pz) = placed.raw
        return self.finish(relative_estimate(self._origin, q, rates, vel, acc, px, py, pz), time_us)

    def _set_origin(self, t: GroundTruth) -> None:
        """The truth `t` (its geodetic and its NED position) becomes the estimate's origin."""
        e = self.estimate
        px, py, pz = t.raw[4]
        e.origin = (t.lat_e7 * 1e-7, t.lon_e7 * 1e-7, t.alt_mm * 1e-3)  # geodetic only once
        self.state[:] = (px, py, pz, math.radians(EARTH_RADIUS_M),
                         math.radians(EARTH_RADIUS_M * math.cos(math.radians(e.origin[0]))), *e.origin)
        self._origin = tuple(self.state.tolist())
        self.has_origin = True

    def finish(self, values: tuple, time_us: int, gps=None) -> Estimate:  # noqa: ANN001
        """The estimate from `relative_estimate`'s values (and the frame's GPS, if any)."""
        e = self.estimate
        e.time_us = time_us
        (e.quaternion_ned_frd, e.angular_velocity_frd_rad_s, e.position_ned_m, e.velocity_ned_m_s,
         e.accel_ned_m_s2, e.lat_deg, e.lon_deg, e.alt_amsl_m) = values
        e.attitude_valid = True
        e.position_valid = True
        if gps is not None:
            e.gps_fix_type, e.gps_satellites = int(gps.fix_type), int(gps.satellites)
            e.gps_eph_cm, e.gps_epv_cm = int(gps.eph_cm), int(gps.epv_cm)
        elif e.gps_fix_type < 3 or e.gps_satellites < 10 or e.gps_eph_cm > 100 or e.gps_epv_cm > 100:
            # no GPS in this frame: at least a good 3D fix (tested first, it holds after once)
            e.gps_fix_type = max(e.gps_fix_type, 3)
            e.gps_satellites = max(e.gps_satellites, 10)
            e.gps_eph_cm, e.gps_epv_cm = min(e.gps_eph_cm, 100), min(e.gps_epv_cm, 100)
        return e


# SensorEstimator.state layout (float64): attitude, gyro bias, position, velocity, accelerometer
# bias (NED), low-passed kinematic acceleration, GPS-derived acceleration, bias-corrected rates,
# declination, end of the alignment (us; NaN before the first step), flags, the origin; the
# baro's zero (baro altitude at local z = 0), its last sample's time (us) and altitude (NaN: none)
_Q, _GYRO_BIAS, _POS, _VEL, _ACC_BIAS, _ACCEL_LP, _GPS_ACCEL, _RATES = 0, 4, 7, 10, 13, 16, 19, 22
_DECLINATION, _ALIGN_UNTIL_US, _HAS_Q, _HAS_ORIGIN, _ORIGIN, _LON_RADIUS = 25, 26, 27, 28, 29, 32
_BARO_OFFSET, _LAST_BARO_US, _LAST_BARO_ALT = 33, 34, 35
ESTIMATOR_STATE = 36
BARO_GAIN_PER_S = 2.0          # 1/s pull of the height to the baro height
BARO_VEL_GAIN_PER_S = 0.5
# SensorEstimator.gains layout
_ACC_KP, _MAG_KP, _GYRO_BIAS_KI, _ALIGN_BOOST, _ALIGN_S = range(5)


@dual
def initial_attitude(ax: float, ay: float, az: float, has_mag: bool, mx: float, my: float, mz: float) -> Quat:
    """Roll/pitch from gravity; yaw from the magnetometer (heading relative to the field)."""
    roll = math.atan2(-ay, -az)
    pitch = math.atan2(ax, math.hypot(ay, az))
    yaw = 0.0
    if has_mag:
        q_rp = quat_from_euler(roll, pitch, 0.0)
        m = quat_rotate(q_rp, (mx, my, mz))
        yaw = -math.atan2(m[1], m[0])
    return quat_from_euler(roll, pitch, yaw)


@kernel(frames, vec)
def estimator_imu_step(s: np.ndarray, k: np.ndarray, ax: float, ay: float, az: float, gx: float, gy: float,
                       gz: float, has_mag: bool, mx: float, my: float, mz: float, dt: float, time_us: int
                       ) -> tuple[Quat, Vec3, Vec3, Vec3, Vec3, float, float, float, bool]:
    """One IMU (+ magnetometer) sample folded into the estimator state `s`: the complementary
    attitude filter, then the accelerometer's prediction of velocity and position. Returns the
    estimate's (attitude, rates, position, velocity, acceleration, lat, lon, alt AMSL) before any
    GPS / baro correction of this step (`SensorEstimator.finish`), and whether the initial
    alignment is over."""
    w0, w1, w2 = gx - s[_GYRO_BIAS], gy - s[_GYRO_BIAS + 1], gz - s[_GYRO_BIAS + 2]
    s[_RATES], s[_RATES + 1], s[_RATES + 2] = w0, w1, w2
    if s[_HAS_Q] == 0.0:
        q0 = initial_attitude(ax, ay, az, has_mag, mx, my, mz)
        s[_Q], s[_Q + 1], s[_Q + 2], s[_Q + 3] = q0
        s[_HAS_Q] = 1.0
    if dt > 0.0:
        _attitude_step(s, k, dt, ax, ay, az, w0, w1, w2, has_mag, mx, my, mz, time_us)
    q = (s[_Q], s[_Q + 1], s[_Q + 2], s[_Q + 3])
    # kinematic acceleration in NED = R f + g
    fn, fe, fd = quat_rotate(q, (ax, ay, az))
    an, ae, ad = fn - s[_ACC_BIAS], fe - s[_ACC_BIAS + 1], fd + GRAVITY_M_S2 - s[_ACC_BIAS + 2]
    if s[_HAS_ORIGIN] != 0.0 and dt > 0.0:
        half_dt = 0.5 * dt
        p, v = _POS, _VEL
        s[p] += (s[v] + an * half_dt) * dt
        s[p + 1] += (s[v + 1] + ae * half_dt) * dt
        s[p + 2] += (s[v + 2] + ad * half_dt) * dt
        s[v] += an * dt
        s[v + 1] += ae * dt
        s[v + 2] += ad * dt
    lp = _ACCEL_LP
    s[lp] += 0.2 * (an - s[lp])
    s[lp + 1] += 0.2 * (ae - s[lp + 1])
    s[lp + 2] += 0.2 * (ad - s[lp + 2])
    return estimate_values(s, time_us)


@dual
def estimate_values(s: np.ndarray, time_us: int) -> tuple[Quat, Vec3, Vec3, Vec3, Vec3, float, float, float, bool]:
    """The estimate that the state `s` holds at `time_us`, as `estimator_imu_step` returns it:
    (attitude, rates, position, velocity, acceleration, lat, lon, alt AMSL, alignment over)."""
    lp = _ACCEL_LP
    return ((s[_Q], s[_Q + 1], s[_Q + 2], s[_Q + 3]), (s[_RATES], s[_RATES + 1], s[_RATES + 2]),
            (s[_POS], s[_POS + 1], s[_POS + 2]), (s[_VEL], s[_VEL + 1], s[_VEL + 2]),
            (s[lp], s[lp + 1], s[lp + 2])) + geodetic(s) + (time_us >= s[_ALIGN_UNTIL_US],)  # NaN: False


@kernel(frames, vec)
def current_values(s: np.ndarray, time_us: int) -> tuple[Quat, Vec3, Vec3, Vec3, Vec3, float, float, float, bool]:
    """`estimate_values`, compiled (for callers that stepped the state in a kernel of their own)."""
    return estimate_values(s, time_us)


@dual
def baro_update(s: np.ndarray, pressure_hpa: float, time_us: int, dt: float) -> None:
    """A barometer sample (hPa) folded into the state `s` (no-op before the origin or without
    time passing). PX4 ignores HIL_SENSOR.pressure_alt: height comes from the pressure itself;
    the first sample sets the baro's zero, the next ones pull the height and vertical velocity."""
    if s[_HAS_ORIGIN] == 0.0 or not dt > 0.0:
        return
    pressure_alt_m = pressure_altitude_m(pressure_hpa * 100.0)
    last = s[_LAST_BARO_US]
    s[_LAST_BARO_US] = time_us
    s[_LAST_BARO_ALT] = pressure_alt_m
    z = s[_POS + 2]
    offset = s[_BARO_OFFSET]
    if offset != offset or last != last:
        s[_BARO_OFFSET] = pressure_alt_m + z   # baro alt at local z = 0
        return
    dt_baro = min(max(time_us - last, 0.0) * 1e-6, 0.5)
    ez = (offset - pressure_alt_m) - z
    s[_POS + 2] = z + min(1.0, BARO_GAIN_PER_S * dt_baro) * ez
    s[_VEL + 2] += min(1.0, BARO_VEL_GAIN_PER_S * dt_baro) * ez


@dual
def position_valid(s: np.ndarray, time_us: int) -> bool:
    """Whether the state's position counts at `time_us` (`Estimate.position_valid`): like EKF2,
    only once the attitude has aligned and the origin is set."""
    return time_us >= s[_ALIGN_UNTIL_US] and s[_HAS_ORIGIN] != 0.0


@dual
def attitude_and_rates(s: np.ndarray) -> tuple[Quat, Vec3]:
    """The estimator state's attitude and bias-corrected body rates (what the inner loop uses)."""
    return (s[_Q], s[_Q + 1], s[_Q + 2], s[_Q + 3]), (s[_RATES], s[_RATES + 1], s[_RATES + 2])


@dual
def geodetic(s: np.ndarray) -> tuple[float, float, float]:
    """(lat deg, lon deg, alt m AMSL) of the estimated position around the origin (0s without one)."""
    if s[_HAS_ORIGIN] == 0.0:
        return 0.0, 0.0, 0.0
    return (s[_ORIGIN] + math.degrees(s[_POS] / EARTH_RADIUS_M), s[_ORIGIN + 1] + math.degrees(s[_POS + 1] / s[_LON_RADIUS]),
            s[_ORIGIN + 2] - s[_POS + 2])


@dual
def _attitude_step(s: np.ndarray, k: np.ndarray, dt: float, ax: float, ay: float, az: float, w0: float, w1: float,
                   w2: float, has_mag: bool, mx: float, my: float, mz: float, time_us: int) -> None:
    qw, qx, qy, qz = s[_Q], s[_Q + 1], s[_Q + 2], s[_Q + 3]
    q = (qw, qx, qy, qz)
    cx = cy = cz = 0.0   # attitude correction (body rates)
    if s[_ALIGN_UNTIL_US] != s[_ALIGN_UNTIL_US]:  # NaN: the first step
        s[_ALIGN_UNTIL_US] = time_us + int(k[_ALIGN_S] * 1e6)
    boost = k[_ALIGN_BOOST] if time_us < s[_ALIGN_UNTIL_US] else 1.0
    a_norm = math.sqrt(ax * ax + ay * ay + az * az)
    # trust the accelerometer's gravity direction only near 1 g
    rx, ry, rz = s[_GPS_ACCEL], s[_GPS_ACCEL + 1], s[_GPS_ACCEL + 2] - GRAVITY_M_S2   # expected specific force, NED
    ref_norm = math.sqrt(rx * rx + ry * ry + rz * rz)
    if 0.5 * GRAVITY_M_S2 < a_norm < 1.5 * GRAVITY_M_S2 and ref_norm > 1.0:
        nx, ny, nz = ax / a_norm, ay / a_norm, az / a_norm  # measured: specific force points up
        ex, ey, ez = quat_rotate_inverse(q, (rx / ref_norm, ry / ref_norm, rz / ref_norm))
        # error = measured x estimated
        g = k[_ACC_KP] * boost
        cx = g * (ny * ez - nz * ey)
        cy = g * (nz * ex - nx * ez)
        cz = g * (nx * ey - ny * ex)
    if has_mag:
        m_ned = quat_rotate(q, (mx, my, mz))
        # heading error about world down, applied in body frame
        heading_err = wrap_pi(s[_DECLINATION] - math.atan2(m_ned[1], m_ned[0]))
        # world down in the body: quat_rotate_inverse(q, (0, 0, 1)) written out
        g = k[_MAG_KP] * boost * heading_err
        cx += 2.0 * (qx * qz - qw * qy) * g
        cy += 2.0 * (qy * qz + qw * qx) * g
        cz += (1.0 - 2.0 * (qx * qx + qy * qy)) * g
    ki = k[_GYRO_BIAS_KI]
    s[_GYRO_BIAS] -= ki * cx * dt
    s[_GYRO_BIAS + 1] -= ki * cy * dt
    s[_GYRO_BIAS + 2] -= ki * cz * dt
    wx, wy, wz = w0 + cx, w1 + cy, w2 + cz
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
    s[_Q], s[_Q + 1], s[_Q + 2], s[_Q + 3] = nw / n, nx / n, ny / n, nz / n


class SensorEstimator:
    """Complementary attitude filter + GPS/baro/accelerometer position filter.

    The per-step part (attitude filter, accelerometer prediction) is the compiled kernel
    `estimator_imu_step` on the float64 `state` vector; the baro correction (50 Hz) is the
    `@dual` `baro_update` on the same vector and the GPS correction (5 Hz) Python (`finish`
    calls both). The fused `direct` loop compiles the per-step part and the baro correction
    into its own step (`estimate_values` then reads the estimate off the state; `refresh`)."""

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
    BARO_OFFSET_SAMPLES = 25       # GPS samples averaged for the baro-to-GPS height offset,
    BARO_OFFSET_GAIN = 0.01        # then tracked slowly (baro drift)
    MIN_GPS_FIX = 3
    MIN_GPS_SATELLITES = 6

    def __init__(self, align_s: float | None = None) -> None:
        self.align_s = self.ALIGN_S if align_s is None else float(align_s)
        self.estimate = Estimate()
        if not hasattr(self, "state"):  # arrays kept over resets (callers may hold them)
            self.state = np.zeros(ESTIMATOR_STATE)
            self.gains = np.zeros(5)
        self.state[:] = 0.0
        self.state[_ALIGN_UNTIL_US] = math.nan
        self.state[_LON_RADIUS] = EARTH_RADIUS_M
        self.state[_BARO_OFFSET:_LAST_BARO_ALT + 1] = math.nan
        g = self.gains
        g[_ACC_KP], g[_MAG_KP], g[_GYRO_BIAS_KI] = self.ACC_KP, self.MAG_KP, self.GYRO_BIAS_KI
        g[_ALIGN_BOOST], g[_ALIGN_S] = self.ALIGN_BOOST, self.align_s
        self.last_time_us: int | None = None
        self._baro_offset_samples = 0
        self._last_gps: tuple[int, Vec3] | None = None

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

    def place(self, spawn: GroundTruth, placed: GroundTruth, time_us: int) -> Estimate:
        """After `reset`: the converged estimate of a vehicle that took off from `spawn` and
        hovers at `placed` (an episode that starts in the air, `StubAutopilot.place_in_air`):
        aligned, the origin where the first GPS fix on the ground would have put it (the
        spawn's geodetic position, without the fix's noise), attitude, position and velocity at
        the truth, no learnt bias (the simulated sensors have none), the declination as
        `_gps_update` looks it up. The baro's zero is taken from the next baro sample (as at
        the first one), tied to this height."""
        s = self.state
        lat, lon, alt = spawn.lat_e7 * 1e-7, spawn.lon_e7 * 1e-7, spawn.alt_mm * 1e-3
        q, rates, vel, _, position = placed.raw
        self.estimate.origin = (lat, lon, alt)
        s[_HAS_ORIGIN], s[_HAS_Q] = 1.0, 1.0
        s[_ORIGIN:_ORIGIN + 3] = (lat, lon, alt)
        s[_LON_RADIUS] = EARTH_RADIUS_M * math.cos(math.radians(lat))
        n, east, _ = magnetic_field_ned_gauss(GeoHome(lat_deg=lat, lon_deg=lon, alt_m=alt))
        s[_DECLINATION] = math.atan2(east, n)
        s[_Q:_Q + 4] = q
        s[_RATES:_RATES + 3] = rates
        s[_POS:_POS + 3] = [p - p0 for p, p0 in zip(position, spawn.raw[4], strict=True)]
        s[_VEL:_VEL + 3] = vel
        s[_GPS_ACCEL:_GPS_ACCEL + 3] = 0.0  # hovering: the expected specific force is gravity's
        s[_ALIGN_UNTIL_US] = time_us  # aligned from now on
        return self.refresh(time_us)

    def step_dt(self, time_us: int) -> float:
        """Seconds since the previous sample (0 for the first); records `time_us`."""
        last = self.last_time_us
        self.last_time_us = time_us
        return 0.0 if last is None else (time_us - last) * 1e-6

    def update(self, frame: SensorFrame) -> Estimate:
        """Fold one SensorFrame into the estimate."""
        time_us = frame.time_us
        dt = self.step_dt(time_us)
        # Python floats: numpy arrays (SensorSuite) index slowly; tuples (HIL client) pass as they are
        ax, ay, az = _floats(frame.accel_frd_m_s2)
        gx, gy, gz = _floats(frame.gyro_frd_rad_s)
        mag = frame.mag_frd_gauss
        if mag is None:
            has_mag, mx, my, mz = False, 0.0, 0.0, 0.0
        else:
            has_mag = True
            mx, my, mz = _floats(mag)
        values = estimator_imu_step(self.state, self.gains, float(ax), float(ay), float(az), float(gx), float(gy),
                                    float(gz), has_mag, float(mx), float(my), float(mz), dt, time_us)
        return self.finish(values, time_us, dt, frame.gps, frame.baro)

    def refresh(self, time_us: int) -> Estimate:
        """The estimate brought up to the state vector at `time_us` (the last sample's time),
        for a caller whose kernel stepped the state without `finish` (`estimator_imu_step`, a
        baro sample's `baro_update`; no GPS sample): what `finish` would have made of those steps."""
        return self.finish(current_values(self.state, time_us), time_us, 0.0, None, None)

    def finish(self, values: tuple, time_us: int, dt: float, gps, baro) -> Estimate:  # noqa: ANN001
        """The step's estimate from `estimator_imu_step`'s values, with this step's GPS and baro
        samples (None when none) folded in."""
        e = self.estimate
        e.time_us = time_us
        (e.quaternion_ned_frd, e.angular_velocity_frd_rad_s, e.position_ned_m, e.velocity_ned_m_s,
         e.accel_ned_m_s2, e.lat_deg, e.lon_deg, e.alt_amsl_m, aligned) = values
        e.attitude_valid = True
        if gps is not None or baro is not None:
            if gps is not None:
                self._gps_update(e, gps)
            if baro is not None:
                baro_update(self.state, baro.pressure_hpa, time_us, dt)
            s = self.state.tolist()  # Python floats: numpy elements read slowly one by one
            e.position_ned_m = (s[_POS], s[_POS + 1], s[_POS + 2])
            e.velocity_ned_m_s = (s[_VEL], s[_VEL + 1], s[_VEL + 2])
            e.lat_deg, e.lon_deg, e.alt_amsl_m = geodetic(s)
        # like EKF2, report a usable position only once the attitude has aligned
        e.position_valid = aligned and e.origin is not None
        return e

    # --- position (GPS, baro: Python on the state vector) ---------------------------------
    def _gps_update(self, e: Estimate, gps) -> None:
        e.gps_fix_type, e.gps_satellites = int(gps.fix_type), int(gps.satellites)
        e.gps_eph_cm, e.gps_epv_cm = int(gps.eph_cm), int(gps.epv_cm)
        if gps.fix_type < self.MIN_GPS_FIX or gps.satellites < self.MIN_GPS_SATELLITES:
            return
        s = self.state
        lat, lon, alt = gps.lat_e7 * 1e-7, gps.lon_e7 * 1e-7, gps.alt_mm * 1e-3
        vel = (gps.vn_cm_s * 0.01, gps.ve_cm_s * 0.01, gps.vd_cm_s * 0.01)
        if self._last_gps is not None and e.time_us > self._last_gps[0]:
            dt_gps = (e.time_us - self._last_gps[0]) * 1e-6
            prev = self._last_gps[1]
            for k in range(3):
                a = float(s[_GPS_ACCEL + k])
                s[_GPS_ACCEL + k] = a + 0.5 * ((vel[k] - prev[k]) / dt_gps - a)
        self._last_gps = (e.time_us, vel)
        if e.origin is None:
            e.origin = (lat, lon, alt)
            s[_HAS_ORIGIN] = 1.0
            s[_ORIGIN:_ORIGIN + 3] = e.origin
            s[_LON_RADIUS] = EARTH_RADIUS_M * math.cos(math.radians(lat))
            s[_POS:_POS + 3] = 0.0
            s[_VEL:_VEL + 3] = vel
            # true heading = magnetic heading + declination (PX4 looks it up in the WMM too)
            n, east, _ = magnetic_field_ned_gauss(GeoHome(lat_deg=lat, lon_deg=lon, alt_m=alt))
            declination = s[_DECLINATION] = math.atan2(east, n)
            if s[_HAS_Q] != 0.0:
                half = 0.5 * declination
                q = tuple(s[_Q:_Q + 4].tolist())
                s[_Q:_Q + 4] = quat_normalize(quat_multiply((math.cos(half), 0.0, 0.0, math.sin(half)), q))
            return
        lat0, lon0, alt0 = e.origin
        meas = (
            math.radians(lat - lat0) * EARTH_RADIUS_M,
            math.radians(lon - lon0) * EARTH_RADIUS_M * math.cos(math.radians(lat0)),
            alt0 - alt,
        )
        baro_offset, last_baro_alt = s[_BARO_OFFSET:_LAST_BARO_ALT + 1:2].tolist()
        has_baro_offset = baro_offset == baro_offset  # NaN: none yet
        if last_baro_alt == last_baro_alt and has_baro_offset:
            # the baro's zero is tied to GPS height: averaged at first, then tracked slowly
            n = self._baro_offset_samples = self._baro_offset_samples + 1
            gain = 1.0 / n if n <= self.BARO_OFFSET_SAMPLES else self.BARO_OFFSET_GAIN
            s[_BARO_OFFSET] = baro_offset + gain * (last_baro_alt + meas[2] - baro_offset)
        # horizontal from GPS; vertical position from baro (PX4 EKF2_HGT_REF=baro), velocity from GPS
        pos, v, bias = s[_POS:_POS + 3].tolist(), s[_VEL:_VEL + 3].tolist(), s[_ACC_BIAS:_ACC_BIAS + 3].tolist()
        for k in range(3):
            if k < 2 or not has_baro_offset:
                ep = meas[k] - pos[k]
                pos[k] += self.GPS_POS_GAIN * ep
                v[k] += self.GPS_POS_TO_VEL * ep
            ev = vel[k] - v[k]
            v[k] += self.GPS_VEL_GAIN * ev
            bias[k] -= self.ACC_BIAS_GAIN * ev
        s[_POS:_POS + 3], s[_VEL:_VEL + 3], s[_ACC_BIAS:_ACC_BIAS + 3] = pos, v, bias
