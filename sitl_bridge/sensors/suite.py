"""`SensorSuite`: one vehicle's IMU, magnetometer, barometer, GPS and ground truth, with
Gazebo-like rates and seeded noise, turned into one `SensorFrame` per physics step.

Rates follow Gazebo-classic's iris: IMU and ground truth every step, magnetometer ~100 Hz
(sampled when at least 10 ms passed: 83 Hz at 4 ms steps, like Gazebo), barometer 50 Hz, GPS
5 Hz. Every sensor is noisy (PX4 marks a sensor STALE when it repeats identical values). Noise
is drawn from the seeded generator in blocks, so the per-step cost is a row lookup. The IMU and
magnetometer synthesis is the compiled kernel `sense` (`sitl_bridge.jit`), which the fused
`direct` loop calls too; baro and GPS (50 Hz, 5 Hz) are Python (`slow_samples`).

Measured position offset (`position_offset_ned_m`, zero unless set): the positions the suite
reports (GPS, barometric altitude, the ground truth sent as HIL_STATE_QUATERNION) are the true
position plus this offset, velocities and attitude unchanged. It lets an episode reset teleport
the vehicle while the autopilot measures a continuous flight (`Lockstep.reset_simulation(...,
continuous=True)`); `reset()` sets it back to zero. It is bounded (`MAX_POSITION_OFFSET_M`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from sitl_bridge import frames
from sitl_bridge.frames import (
    enu_to_ned_xyz,
    flu_to_frd_xyz,
    quat_enu_flu_to_ned_frd_t,
    quat_rotate_inverse_t,
)
from sitl_bridge.jit import dual, kernel
from sitl_bridge.physics import state as state_layout
from sitl_bridge.physics.simulation import VehicleState
from sitl_bridge.physics.state import ACCEL, FORCE_FLU, OMEGA_FLU, POS, QUAT, RAW_SIZE, VEL
from sitl_bridge.sensors.environment import (
    KELVIN_OFFSET,
    isa_pressure_pa,
    isa_temperature_k,
    magnetic_field_ned_gauss,
    pressure_altitude_m,
)
from sitl_bridge.sensors.geodesy import Projection
from sitl_bridge.world.clock import DEFAULT_STEP_US
from sitl_bridge.world.schema import GeoHome

# PX4's simulated IMU FIFO stores int16 counts: clamp to its ranges (16 g, 2000 deg/s)
ACCEL_LIMIT_M_S2 = 156.0
GYRO_LIMIT_RAD_S = 34.9

MAX_POSITION_OFFSET_M = (300.0, 20.0)
"""Largest (horizontal, vertical) measured position offset a continuous reset may build up.
Why bounded: the magnetic field is the home's (`magnetic_field_ned_gauss(home)`) while the
autopilot looks up its own field model at the position it measures, so the two drift apart
with distance (negligible within a few hundred metres of home); and a vertical offset moves
the autopilot's idea of its height above home (and the barometric altitude it flies at) away
from the truth, which its ground and landing logic use. Past the bound the caller restarts
the autopilot instead (its estimator then starts again from the truth)."""


@dataclass(frozen=True)
class SensorRates:
    """Sample rates (Hz) of the slower sensors; the IMU and ground truth run every step."""

    mag_hz: float = 100.0
    baro_hz: float = 50.0
    gps_hz: float = 5.0


@dataclass(frozen=True)
class SensorNoise:
    """White-noise levels. IMU and mag are noise densities (per sqrt(Hz), Gazebo's current
    IIM42653 / iris defaults), scaled by each sample period; the others are per-sample sigmas."""

    gyro_density_rad_s_sqrt_hz: float = 8.727e-4
    accel_density_m_s2_sqrt_hz: float = 6.37e-3
    mag_density_gauss_sqrt_hz: float = 4e-4
    baro_pa: float = 1.0
    gps_horizontal_m: float = 0.02
    gps_vertical_m: float = 0.04
    gps_velocity_horizontal_m_s: float = 0.02
    gps_velocity_vertical_m_s: float = 0.04
    gps_eph_cm: int = 100
    gps_epv_cm: int = 100
    gps_satellites: int = 10


@dataclass(frozen=True)
class BaroSample:
    """Barometer reading as HIL_SENSOR carries it."""

    pressure_hpa: float
    temperature_c: float
    pressure_alt_m: float


@dataclass(frozen=True)
class GpsSample:
    """GPS fix in HIL_GPS units: degE7, mm (AMSL), cm, cm/s (NED), centidegrees."""

    lat_e7: int
    lon_e7: int
    alt_mm: int
    eph_cm: int
    epv_cm: int
    vel_cm_s: int
    vn_cm_s: int
    ve_cm_s: int
    vd_cm_s: int
    cog_cdeg: int
    fix_type: int
    satellites: int


@dual
def truth_of(position_enu: tuple, q_enu_flu: tuple, velocity_enu: tuple, omega_flu: tuple, accel_enu: tuple
             ) -> tuple[tuple[float, ...], ...]:
    """The ground truth in PX4's frames, from ENU / FLU state: (quaternion NED/FRD, angular
    velocity FRD, velocity NED, acceleration NED, position NED), plain-float tuples."""
    return (quat_enu_flu_to_ned_frd_t(q_enu_flu), flu_to_frd_xyz(omega_flu[0], omega_flu[1], omega_flu[2]),
            enu_to_ned_xyz(velocity_enu[0], velocity_enu[1], velocity_enu[2]),
            enu_to_ned_xyz(accel_enu[0], accel_enu[1], accel_enu[2]),
            enu_to_ned_xyz(position_enu[0], position_enu[1], position_enu[2]))


@dual
def truth_of_vector(x: np.ndarray) -> tuple[tuple[float, ...], ...]:
    """`truth_of` a state vector (`physics.state` layout)."""
    return truth_of((x[POS], x[POS + 1], x[POS + 2]), (x[QUAT], x[QUAT + 1], x[QUAT + 2], x[QUAT + 3]),
                    (x[VEL], x[VEL + 1], x[VEL + 2]), (x[OMEGA_FLU], x[OMEGA_FLU + 1], x[OMEGA_FLU + 2]),
                    (x[ACCEL], x[ACCEL + 1], x[ACCEL + 2]))


class GroundTruth:
    """Noise-free state in PX4's frames (what HIL_STATE_QUATERNION carries). Immutable.

    Built every step but evaluated lazily: the arrays and the geodetic position are computed
    on first access, so a consumer that ignores the truth costs (almost) nothing. `raw` holds
    the same values as plain-float tuples (quaternion, angular velocity, velocity,
    acceleration, position) for per-step consumers that want to skip numpy.
    """

    def __init__(self, quaternion_ned_frd, angular_velocity_frd_rad_s, lat_e7: int, lon_e7: int, alt_mm: int,
                 velocity_ned_m_s, accel_ned_m_s2, position_ned_m) -> None:
        self.__dict__["raw"] = (tuple(quaternion_ned_frd), tuple(angular_velocity_frd_rad_s),
                                tuple(velocity_ned_m_s), tuple(accel_ned_m_s2), tuple(position_ned_m))
        self._projection: Projection | None = None
        self._state: VehicleState | None = None
        self.__dict__.update(lat_e7=int(lat_e7), lon_e7=int(lon_e7), alt_mm=int(alt_mm))

    @classmethod
    def _lazy(cls, values: tuple, projection: Projection) -> GroundTruth:
        truth = cls.__new__(cls)
        truth.__dict__["raw"] = values
        truth._projection = projection
        truth._state = None
        return truth

    @classmethod
    def _of_state(cls, state: VehicleState, projection: Projection,
                  offset_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> GroundTruth:
        """The truth of a vehicle state, converted to PX4's frames only when first read; its
        position shifted by the suite's measured position offset (module docstring)."""
        truth = cls.__new__(cls)
        truth._projection = projection
        truth._state = state
        truth._offset_ned = offset_ned_m
        return truth

    @cached_property
    def raw(self) -> tuple[tuple[float, ...], ...]:  # set directly unless built from a state
        """(quaternion, angular velocity, velocity, acceleration, position) in NED / FRD as
        plain-float tuples."""
        assert self._state is not None
        position_enu, q_enu_flu, velocity_enu, omega_flu, _, accel_enu = self._state.raw
        raw = truth_of(position_enu, q_enu_flu, velocity_enu, omega_flu, accel_enu)
        on, oe, od = self._offset_ned
        if on or oe or od:
            pn, pe, pd = raw[4]
            raw = (*raw[:4], (pn + on, pe + oe, pd + od))
        return raw

    def __repr__(self) -> str:
        return (f"GroundTruth(position_ned_m={self.raw[4]}, velocity_ned_m_s={self.raw[2]}, "
                f"quaternion_ned_frd={self.raw[0]})")

    @cached_property
    def quaternion_ned_frd(self) -> np.ndarray:
        """(w, x, y, z), rotates FRD into NED."""
        return _readonly(self.raw[0])

    @cached_property
    def angular_velocity_frd_rad_s(self) -> np.ndarray:
        return _readonly(self.raw[1])

    @cached_property
    def velocity_ned_m_s(self) -> np.ndarray:
        return _readonly(self.raw[2])

    @cached_property
    def accel_ned_m_s2(self) -> np.ndarray:
        """Coordinate acceleration (not specific force)."""
        return _readonly(self.raw[3])

    @cached_property
    def position_ned_m(self) -> np.ndarray:
        return _readonly(self.raw[4])

    @cached_property
    def _geodetic(self) -> tuple[int, int, int]:
        assert self._projection is not None
        lat, lon, alt = self._projection.to_geodetic(*self.raw[4])
        return int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000.0))

    @cached_property
    def lat_e7(self) -> int:
        return self._geodetic[0]

    @cached_property
    def lon_e7(self) -> int:
        return self._geodetic[1]

    @cached_property
    def alt_mm(self) -> int:
        """Altitude AMSL in mm."""
        return self._geodetic[2]


def _readonly(values) -> np.ndarray:
    array = np.array(values, dtype=float)
    array.flags.writeable = False
    return array


@dataclass
class SensorFrame:
    """Everything the sensors produced at one physics step."""

    time_us: int
    accel_frd_m_s2: np.ndarray
    gyro_frd_rad_s: np.ndarray
    mag_frd_gauss: np.ndarray | None      # None when not updated this step
    baro: BaroSample | None
    gps: GpsSample | None
    truth: GroundTruth


class _NoiseBlock:
    """Standard normal draws, `columns` per sample, drawn `rows` at a time from one generator
    (one numpy call per block instead of one per sample). `array` row `next` is the next sample."""

    def __init__(self, rng: np.random.Generator, columns: int, rows: int) -> None:
        self._rng = rng
        self._columns = columns
        self.rows = rows
        self.array = np.zeros((1, columns))
        self.next = rows  # empty: the first take() draws a block

    def refill(self) -> None:
        self.array = self._rng.standard_normal((self.rows, self._columns))
        self.next = 0

    def take_row(self) -> int:
        """Index of the next sample in `array` (drawing a new block when this one is used up)."""
        if self.next >= self.rows:
            self.refill()
        row = self.next
        self.next = row + 1
        return row

    def take(self) -> list[float]:
        return self.array[self.take_row()].tolist()

def offset_within_bounds(offset_ned_m: tuple[float, float, float]) -> bool:
    """Whether a measured position offset is within `MAX_POSITION_OFFSET_M`."""
    north, east, down = offset_ned_m
    horizontal, vertical = MAX_POSITION_OFFSET_M
    return math.hypot(north, east) <= horizontal and abs(down) <= vertical


@dual
def _clamp(x: float, limit: float) -> float:
    return limit if x > limit else -limit if x < -limit else x


_WARM = False  # the `sense` kernel is loaded in this process

# SensorSuite.constants layout (the `sense` kernel's)
_SIGMA_ACCEL, _SIGMA_GYRO, _SIGMA_MAG, _FIELD_NED = 0, 1, 2, 3
SENSE_CONSTANTS = 6


@kernel(frames, state_layout)
def sense(x: np.ndarray, imu_noise: np.ndarray, imu_row: int, mag_noise: np.ndarray, mag_row: int,
          c: np.ndarray) -> tuple[float, ...]:
    """IMU (and, when `mag_row` >= 0, magnetometer) sample of the vehicle state vector `x`
    (`physics.state` layout): (accel FRD x3, gyro FRD x3, mag FRD gauss x3; 0 without mag).
    Specific force and rates in FRD plus white noise, clamped to PX4's FIFO range; the field
    (NED) rotated into the body plus white noise."""
    n = imu_noise[imu_row]
    sa, sg = c[_SIGMA_ACCEL], c[_SIGMA_GYRO]
    # FLU -> FRD (x, -y, -z) written out
    fx, fy, fz = x[FORCE_FLU], x[FORCE_FLU + 1], x[FORCE_FLU + 2]
    gx, gy, gz = x[OMEGA_FLU], -x[OMEGA_FLU + 1], -x[OMEGA_FLU + 2]
    a0, a1, a2 = fx + sa * n[0], sa * n[1] - fy, sa * n[2] - fz
    g0, g1, g2 = gx + sg * n[3], gy + sg * n[4], gz + sg * n[5]
    a_max, g_max = ACCEL_LIMIT_M_S2, GYRO_LIMIT_RAD_S
    if not (-a_max < a0 < a_max and -a_max < a1 < a_max and -a_max < a2 < a_max
            and -g_max < g0 < g_max and -g_max < g1 < g_max and -g_max < g2 < g_max):
        a0, a1, a2 = _clamp(a0, a_max), _clamp(a1, a_max), _clamp(a2, a_max)
        g0, g1, g2 = _clamp(g0, g_max), _clamp(g1, g_max), _clamp(g2, g_max)
    m0 = m1 = m2 = 0.0
    if mag_row >= 0:
        q_ned_frd = quat_enu_flu_to_ned_frd_t((x[QUAT], x[QUAT + 1], x[QUAT + 2], x[QUAT + 3]))
        f = _FIELD_NED
        bx, by, bz = quat_rotate_inverse_t(q_ned_frd, (c[f], c[f + 1], c[f + 2]))
        m = mag_noise[mag_row]
        s = c[_SIGMA_MAG]
        m0, m1, m2 = bx + s * m[0], by + s * m[1], bz + s * m[2]
    return a0, a1, a2, g0, g1, g2, m0, m1, m2


class SensorSuite:
    """One vehicle's sensors. Call `sample` once per physics step, in step order.

    Args:
        home: geodetic origin of the world (for GPS, baro altitude and the magnetic field).
        seed: seeds every noise stream of this suite (use a different seed per vehicle).
        step_us: physics step, for the IMU noise scaling.
        rates / noise: sensor rates and noise levels.
    """

    def __init__(self, home: GeoHome, *, seed: int, step_us: int = DEFAULT_STEP_US, rates: SensorRates | None = None,
                 noise: SensorNoise | None = None) -> None:
        self.home = home
        self.step_us = step_us
        self.rates = rates or SensorRates()
        self.noise = noise or SensorNoise()
        self._projection = Projection(home)
        self._field_ned = magnetic_field_ned_gauss(home)
        n = self.noise
        step_s = step_us * 1e-6
        self._sigma_gyro = n.gyro_density_rad_s_sqrt_hz / math.sqrt(step_s)
        self._sigma_accel = n.accel_density_m_s2_sqrt_hz / math.sqrt(step_s)
        self._mag_period_us = int(round(1e6 / self.rates.mag_hz))
        self._baro_period_us = int(round(1e6 / self.rates.baro_hz))
        self._gps_period_us = int(round(1e6 / self.rates.gps_hz))
        # the period actually achieved is a whole number of steps at or above the nominal one
        mag_steps = max(1, -(-self._mag_period_us // step_us))
        self._sigma_mag = n.mag_density_gauss_sqrt_hz / math.sqrt(mag_steps * step_s)
        c = self.constants = np.zeros(SENSE_CONSTANTS)
        c[_SIGMA_ACCEL], c[_SIGMA_GYRO], c[_SIGMA_MAG] = self._sigma_accel, self._sigma_gyro, self._sigma_mag
        c[_FIELD_NED:_FIELD_NED + 3] = self._field_ned
        self._seed = seed
        self._offset_ned = (0.0, 0.0, 0.0)
        self.reset(seed)
        global _WARM
        if not _WARM:  # load (or compile) the kernel now, not at the first sample
            sense(np.zeros(RAW_SIZE), np.zeros((1, 6)), 0, np.zeros((1, 3)), 0, self.constants)
            _WARM = True

    @property
    def position_offset_ned_m(self) -> tuple[float, float, float]:
        """Added to the true position in every position the suite reports (see module doc)."""
        return self._offset_ned

    @position_offset_ned_m.setter
    def position_offset_ned_m(self, offset: tuple[float, float, float]) -> None:
        north, east, down = (float(c) for c in offset)
        if not offset_within_bounds((north, east, down)):
            raise ValueError(f"position offset {offset} beyond MAX_POSITION_OFFSET_M {MAX_POSITION_OFFSET_M}")
        self._offset_ned = (north, east, down)

    def reset(self, seed: int | None = None) -> None:
        """Restart the noise streams (re-seeded when `seed` is given) and the sample schedule;
        the position offset back to zero."""
        if seed is not None:
            self._seed = seed
        self._offset_ned = (0.0, 0.0, 0.0)
        rng = np.random.default_rng(self._seed)
        self.imu_noise = _NoiseBlock(rng, 6, 2048)
        self.mag_noise = _NoiseBlock(rng, 3, 512)
        self._baro_noise = _NoiseBlock(rng, 1, 512)
        self._gps_noise = _NoiseBlock(rng, 6, 128)
        self._next_mag_us = self._next_baro_us = self._next_gps_us = -(2**62)
        self.next_slow_us = -(2**62)
        """The earliest time a magnetometer, baro or GPS sample is due (`slow_samples`)."""

    def sample(self, state: VehicleState, time_us: int) -> SensorFrame:
        """The sensor frame for the vehicle state at `time_us` (after the physics step)."""
        a0, a1, a2, g0, g1, g2, mag, baro, gps = self.sample_values(state.vector, time_us)
        return SensorFrame(time_us, np.array((a0, a1, a2)), np.array((g0, g1, g2)),
                           None if mag is None else np.array(mag), baro, gps, self.ground_truth(state))

    def sample_values(self, x: np.ndarray, time_us: int) -> tuple:
        """`sample` as plain values, for the per-step HIL link (no arrays, no frame): (accel FRD
        x3, gyro FRD x3, mag FRD tuple or None, baro or None, GPS or None) of the state vector
        `x` (`physics.state` layout). Draws the same noise as `sample`: use one or the other."""
        imu_row = self.imu_noise.take_row()
        mag_row, baro, gps = self.slow_samples(x, time_us) if time_us >= self.next_slow_us else (-1, None, None)
        a0, a1, a2, g0, g1, g2, m0, m1, m2 = sense(x, self.imu_noise.array, imu_row, self.mag_noise.array, mag_row,
                                                   self.constants)
        return a0, a1, a2, g0, g1, g2, (m0, m1, m2) if mag_row >= 0 else None, baro, gps

    def ground_truth(self, state: VehicleState) -> GroundTruth:
        """The ground truth of `state` as `sample` reports it (lazy; the measured position
        offset applied)."""
        return GroundTruth._of_state(state, self._projection, self._offset_ned)

    def slow_samples(self, x: np.ndarray, time_us: int) -> tuple[int, BaroSample | None, GpsSample | None]:
        """The slower sensors due at `time_us` for the state vector `x` (`physics.state`
        layout): (the magnetometer's noise row for `sense`, -1 when not due; baro; GPS). Call
        once per step, after the IMU's noise row was taken, when `time_us >= next_slow_us`."""
        mag_row = -1
        if time_us >= self._next_mag_us:
            self._next_mag_us = time_us + self._mag_period_us
            mag_row = self.mag_noise.take_row()
        baro = gps = None
        if time_us >= self._next_baro_us or time_us >= self._next_gps_us:
            pe, pn, pu, ve, vn, vu = (x[POS:POS + 3].tolist() + x[VEL:VEL + 3].tolist())
            on, oe, od = self._offset_ned  # the measured position (module docstring)
            pn, pe, pu = pn + on, pe + oe, pu - od
            if time_us >= self._next_baro_us:
                self._next_baro_us = time_us + self._baro_period_us
                alt_m = self.home.alt_m + pu
                pressure_pa = isa_pressure_pa(alt_m) + self.noise.baro_pa * self._baro_noise.take()[0]
                baro = BaroSample(pressure_hpa=pressure_pa * 0.01,
                                  temperature_c=isa_temperature_k(alt_m) - KELVIN_OFFSET,
                                  pressure_alt_m=pressure_altitude_m(pressure_pa))
            if time_us >= self._next_gps_us:
                self._next_gps_us = time_us + self._gps_period_us
                gps = self._gps(pn, pe, -pu, vn, ve, -vu)
        self.next_slow_us = min(self._next_mag_us, self._next_baro_us, self._next_gps_us)
        return mag_row, baro, gps

    def truth_frame(self, state: VehicleState, time_us: int) -> SensorFrame:
        """Ground truth only, for an autopilot that flies on it (the envs' `ground_truth`
        estimator): no sensor is simulated and no noise drawn; accel/gyro carry the noise-free
        specific force and rates (FRD tuples), mag/baro/GPS are None. Not a PX4 input."""
        position_enu, q_enu_flu, velocity_enu, omega_flu, force_flu, accel_enu = state.raw
        values = truth_of(position_enu, q_enu_flu, velocity_enu, omega_flu, accel_enu)
        truth = GroundTruth._lazy(values, self._projection)
        return SensorFrame(time_us, flu_to_frd_xyz(*force_flu), values[1], None, None, None, truth)  # type: ignore[arg-type]

    def _gps(self, pn: float, pe: float, pd: float, vn: float, ve: float, vd: float) -> GpsSample:
        n = self.noise
        z = self._gps_noise.take()
        lat, lon, alt = self._projection.to_geodetic(pn + n.gps_horizontal_m * z[0], pe + n.gps_horizontal_m * z[1],
                                                     pd + n.gps_vertical_m * z[2])
        vn += n.gps_velocity_horizontal_m_s * z[3]
        ve += n.gps_velocity_horizontal_m_s * z[4]
        vd += n.gps_velocity_vertical_m_s * z[5]
        cog = math.degrees(math.atan2(ve, vn)) % 360.0
        return GpsSample(
            lat_e7=int(round(lat * 1e7)), lon_e7=int(round(lon * 1e7)), alt_mm=int(round(alt * 1000.0)),
            eph_cm=n.gps_eph_cm, epv_cm=n.gps_epv_cm,
            vel_cm_s=int(round(math.hypot(vn, ve) * 100.0)),
            vn_cm_s=int(round(vn * 100.0)), ve_cm_s=int(round(ve * 100.0)), vd_cm_s=int(round(vd * 100.0)),
            cog_cdeg=int(round(cog * 100.0)) % 36000, fix_type=3, satellites=n.gps_satellites,
        )
