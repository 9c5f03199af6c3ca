"""The stub's usual simulator step in two compiled calls (`HilClient`'s fast path).

A lockstep step brings one read of whole frames: HIL_SENSOR (primary sensor), with HIL_GPS at
the GPS rate. For exactly that, `FusedSensorStep.handle` replaces the per-message path (frame
parser, struct decode, SensorFrame, `StubAutopilot.update`, struct pack, frame encoder) with:

* `sensor_estimate`: check and decode the frames (MAVLink 2 framing and checksum, zero-extended
  truncated payloads), then the estimator's own compiled `estimator_imu_step`;
* Python at 50 / 5 Hz: the baro and GPS corrections (`SensorEstimator.finish`), and every
  step the commander and position loop (`StubAutopilot.prepare`), as the `direct` backend does;
* `actuator_frame`: the stub's `inner_loop` (attitude, rates, mixer) on the estimator state's
  attitude and rates (`attitude_and_rates`, as `direct`'s fused loop), then the
  HIL_ACTUATOR_CONTROLS frame, into a buffer that goes to the socket as it is.
* in a steady step (`Commander.steady`), `steady_actuator_frame` instead of the commander and
  position loop in Python and `actuator_frame`: the commander's `steady_output` test, the stub's
  `steady_step` (position loop when due, `inner_loop`; motors off when disarmed), then the same
  frame (as `direct`'s `vehicle_step`); when the commander has something to decide, it writes
  nothing and the step goes on in Python as above.

The same components as the per-message path, in the same order: the answers are the same bytes
(tests/test_stub_hil_fused.py). Anything else (a split or extra frame, garbage, signing, another
sensor or GPS instance, ground truth, the ground-truth estimator) leaves the state untouched and
takes the per-message path.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from sitl_bridge import frames, mavlink_kernels
from sitl_bridge.jit import dual, kernel
from sitl_bridge.mavlink_kernels import (
    ACT_CRC,
    ACT_ID,
    ACT_LEN,
    FIELDS_BARO,
    FIELDS_MAG,
    GPS_CRC,
    GPS_ID,
    GPS_LEN,
    HEADER,
    SCRATCH_BYTES,
    SENSOR_CRC,
    SENSOR_ID,
    SENSOR_LEN,
    checked_frame,
    float32_value,
    write_frame,
)
from sitl_bridge.sensors import BaroSample, GpsSample

from . import commander as commander_module
from . import control, mixer, vec
from .autopilot import inner_loop, inner_loop_kernel, steady_step
from .commander import NOT_STEADY, STEADY_OFF, steady_output
from .estimator import attitude_and_rates, estimate_values, estimator_imu_step, position_valid

if TYPE_CHECKING:
    from collections.abc import Callable

    from .autopilot import StubAutopilot
    from .estimator import Estimate

HANDLED, WITH_BARO, WITH_GPS = 1, 2, 4
FRAME_BYTES = HEADER + ACT_LEN + 2


@kernel(frames, vec, mavlink_kernels, estimator_imu_step)
def sensor_estimate(
    data: bytes, s: np.ndarray, k: np.ndarray, last_us: int, scratch: np.ndarray, gps: np.ndarray
) -> tuple:
    """(status, time_us, dt, baro pressure hPa, `estimator_imu_step`'s values) of one read that is
    exactly HIL_SENSOR (id 0) [+ HIL_GPS (id 0)]: status HANDLED | WITH_BARO | WITH_GPS (the GPS
    fields into `gps` in `GpsSample` order), or 0 and nothing changed. `last_us`: the estimator's
    previous sample, -1 for none."""
    none = (
        (1.0, 0.0, 0.0, 0.0),
        (0.0, 0.0, 0.0),
        (0.0, 0.0, 0.0),
        (0.0, 0.0, 0.0),
        (0.0, 0.0, 0.0),
        0.0,
        0.0,
        0.0,
        False,
    )
    end = checked_frame(data, 0, SENSOR_ID, SENSOR_CRC, SENSOR_LEN, scratch)
    if end < 0 or scratch[64] != 0:  # not a (primary) HIL_SENSOR
        return 0, 0, 0.0, 0.0, none
    u = scratch.view(np.uint32)
    ax, ay, az = float32_value(u[2]), float32_value(u[3]), float32_value(u[4])
    gx, gy, gz = float32_value(u[5]), float32_value(u[6]), float32_value(u[7])
    mx, my, mz, pressure = (
        float32_value(u[8]),
        float32_value(u[9]),
        float32_value(u[10]),
        float32_value(u[11]),
    )
    fields = u[15]
    time_us = scratch.view(np.int64)[0]
    status = HANDLED
    if end < len(data):
        if (
            checked_frame(data, end, GPS_ID, GPS_CRC, GPS_LEN, scratch) != len(data)
            or scratch[36] != 0
        ):
            return 0, 0, 0.0, 0.0, none
        i32, u16, i16 = scratch.view(np.int32), scratch.view(np.uint16), scratch.view(np.int16)
        gps[0], gps[1], gps[2] = i32[2], i32[3], i32[4]  # lat, lon, alt
        gps[3], gps[4], gps[5] = u16[10], u16[11], u16[12]  # eph, epv, vel
        gps[6], gps[7], gps[8] = i16[13], i16[14], i16[15]  # vn, ve, vd
        gps[9], gps[10], gps[11] = u16[16], scratch[34], scratch[35]  # cog, fix type, satellites
        status |= WITH_GPS
    if fields & FIELDS_BARO == FIELDS_BARO:
        status |= WITH_BARO
    dt = 0.0 if last_us < 0 else (time_us - last_us) * 1e-6
    values = estimator_imu_step(
        s, k, ax, ay, az, gx, gy, gz, fields & FIELDS_MAG == FIELDS_MAG, mx, my, mz, dt, time_us
    )
    return status, time_us, dt, pressure, values


@kernel(frames, vec, mavlink_kernels, control, mixer, inner_loop_kernel, estimator_imu_step)
def actuator_frame(
    out: np.ndarray,
    scratch: np.ndarray,
    sequence: int,
    system_id: int,
    component_id: int,
    time_us: int,
    fly: bool,
    armed: bool,
    ctl: np.ndarray,
    att_gains: np.ndarray,
    rate_state: np.ndarray,
    rate_gains: np.ndarray,
    mix_constants: np.ndarray,
    mix_state: np.ndarray,
    est_state: np.ndarray,
    yaw_rate_ff: float,
    dt_s: float,
    landed: bool,
) -> int:
    """With `fly`, the inner loop (`inner_loop`, outputs also into `ctl`);
    then the HIL_ACTUATOR_CONTROLS frame answering `time_us` into `out` (motors 0 unless flying;
    armed or disarmed mode; lockstep flag). Returns the frame's length."""
    u0 = u1 = u2 = u3 = 0.0
    if fly:
        q, rates = attitude_and_rates(est_state)
        u0, u1, u2, u3 = inner_loop(
            ctl,
            att_gains,
            rate_state,
            rate_gains,
            mix_constants,
            mix_state,
            q,
            rates,
            yaw_rate_ff,
            dt_s,
            landed,
        )
    return actuator_message(out, scratch, sequence, system_id, component_id, time_us, armed, u0, u1, u2, u3)


@kernel(frames, vec, mavlink_kernels, control, mixer, inner_loop_kernel, estimator_imu_step, commander_module)
def steady_actuator_frame(
    out: np.ndarray,
    scratch: np.ndarray,
    sequence: int,
    system_id: int,
    component_id: int,
    time_us: int,
    plan: np.ndarray,
    last_us: int,
    last_run_us: int,
    ctl: np.ndarray,
    att_gains: np.ndarray,
    rate_state: np.ndarray,
    rate_gains: np.ndarray,
    mix_constants: np.ndarray,
    mix_state: np.ndarray,
    est_state: np.ndarray,
    pc_state: np.ndarray,
    pc_gains: np.ndarray,
) -> tuple[int, bool, bool]:
    """A steady commander's step on this step's estimate (the estimator state, `finish` done):
    when `steady_output` finds one, `steady_step` (or motors off) and the HIL_ACTUATOR_CONTROLS
    frame into `out`; returns (the frame's length, whether the position loop ran, whether
    flying), or (0, False, False) with nothing changed when the commander must decide."""
    q, rates, pos, vel, acc, _, _, _, _ = estimate_values(est_state, time_us)
    output = steady_output(plan, time_us, pos[2], vel[0], vel[1], vel[2], position_valid(est_state, time_us))
    if output == NOT_STEADY:
        return 0, False, False
    if output == STEADY_OFF:
        return actuator_message(out, scratch, sequence, system_id, component_id, time_us, False, 0.0, 0.0, 0.0,
                                0.0), False, False
    outer_ran, u0, u1, u2, u3 = steady_step(plan, ctl, pc_state, pc_gains, att_gains, rate_state, rate_gains,
                                            mix_constants, mix_state, q, rates, pos, vel, acc, time_us, last_us,
                                            last_run_us)
    size = actuator_message(out, scratch, sequence, system_id, component_id, time_us, True, u0, u1, u2, u3)
    return size, outer_ran, True


@dual
def actuator_message(out: np.ndarray, scratch: np.ndarray, sequence: int, system_id: int, component_id: int,
                     time_us: int, armed: bool, u0: float, u1: float, u2: float, u3: float) -> int:
    """The HIL_ACTUATOR_CONTROLS frame answering `time_us` with motors 1..4 = u into `out`
    (armed or disarmed mode; lockstep flag). Returns the frame's length."""
    scratch[:] = 0
    f = scratch.view(np.float32)
    f[4], f[5], f[6], f[7] = u0, u1, u2, u3
    w = scratch.view(np.int64)
    w[0], w[1] = time_us, 1  # time, flags: lockstep
    scratch[ACT_LEN - 1] = 129 if armed else 1  # custom mode enabled | safety armed
    return write_frame(out, 0, scratch, ACT_LEN, sequence, system_id, component_id, ACT_ID, ACT_CRC)


class FusedStep(NamedTuple):
    """What one handled step made: the HIL_ACTUATOR_CONTROLS frame for the caller to send, and
    what it read (for the caller's counters)."""

    frame: memoryview
    time_us: int
    frames_read: int
    with_gps: bool


class FusedSensorStep:
    """`HilClient`'s fast path (module docstring): `handle` answers a read with the frame to send,
    or declines it. It owns no socket, parser or encoder: the client sends and counts."""

    def __init__(self, autopilot: StubAutopilot, system_id: int, component_id: int) -> None:
        self.autopilot = autopilot
        self._scratch = np.zeros(SCRATCH_BYTES, np.uint8)
        self._gps = np.zeros(12, np.int64)
        self._out = np.zeros(FRAME_BYTES, np.uint8)
        self._view = memoryview(self._out)
        self._ids = (system_id, component_id)
        self._rate = self._attitude = None
        self._vectors: tuple = ()
        self.warm_up()

    def warm_up(self) -> None:
        """Load (or compile) both kernels on scratch state, not at the first step."""
        ap = self.autopilot
        est = ap.estimator
        ap.refresh_gains()  # the steady step divides by some of them
        level = est.state.copy()
        level[0] = 1.0  # an attitude (w, x, y, z) to control: the identity
        sensor_estimate(b"", est.state.copy(), est.gains, -1, self._scratch, self._gps)
        actuator_frame(
            self._out,
            self._scratch,
            0,
            1,
            1,
            0,
            False,
            False,
            ap.control.copy(),
            ap.attitude_control.gains,
            ap.rate_control.state.copy(),
            ap.rate_control.gains,
            ap.mixer.constants,
            ap.mixer.state.copy(),
            est.state.copy(),
            0.0,
            0.0,
            False,
        )
        scratch_plan = ap.commander.plan.copy()
        scratch_plan[:] = np.nan  # no offboard or takeoff test, no descent: flies (on scratch copies)
        steady_actuator_frame(
            self._out,
            self._scratch,
            0,
            1,
            1,
            4000,
            scratch_plan,
            -1,
            -1,
            ap.control.copy(),
            ap.attitude_control.gains,
            ap.rate_control.state.copy(),
            ap.rate_control.gains,
            ap.mixer.constants,
            ap.mixer.state.copy(),
            level,
            ap.position_control.state.copy(),
            ap.position_control.gains,
        )

    def _operands(self, ap: StubAutopilot) -> tuple:
        """`actuator_frame`'s state and gain vectors (new ones after `StubAutopilot.reset`)."""
        if ap.rate_control is not self._rate or ap.attitude_control is not self._attitude:
            self._rate, self._attitude = rate, attitude = ap.rate_control, ap.attitude_control
            self._vectors = (
                ap.control,
                attitude.gains,
                rate.state,
                rate.gains,
                ap.mixer.constants,
                ap.mixer.state,
                ap.estimator.state,
                ap.position_control.state,
                ap.position_control.gains,
            )
        return self._vectors

    def handle(self, data: bytes, take_sequence: Callable[[], int]) -> FusedStep | None:
        """Answer `data` when it is one usual step, else None with nothing changed.
        `take_sequence` gives the answer's MAVLink sequence number (taken only for an answer)."""
        ap = self.autopilot
        est = ap.estimator
        last = est.last_time_us
        status, time_us, dt, pressure_hpa, values = sensor_estimate(
            data, est.state, est.gains, -1 if last is None else last, self._scratch, self._gps
        )
        if not status:
            return None
        est.last_time_us = time_us
        gps = baro = None
        if status != HANDLED:
            if status & WITH_GPS:
                gps = GpsSample(*self._gps.tolist())
            if status & WITH_BARO:
                baro = BaroSample(pressure_hpa, 0.0, 0.0)  # the estimator reads the pressure only
        e = est.finish(values, time_us, dt, gps, baro)
        sequence = take_sequence()
        size = 0
        commander = ap.commander
        if commander.steady and ap.gains_current:
            size, outer_ran, flying = steady_actuator_frame(
                self._out, self._scratch, sequence, *self._ids, time_us, commander.plan, *ap.clock_us(),
                *self._operands(ap)
            )
            if size:
                ap.flew_steady(time_us, outer_ran, flying)
        if not size:
            size = self._actuators(ap, e, sequence, time_us)
        return FusedStep(self._view[:size], time_us, 1 if gps is None else 2, gps is not None)

    def _actuators(self, ap: StubAutopilot, e: Estimate, sequence: int, time_us: int) -> int:
        """The commander and position loop in Python (`prepare`), then `actuator_frame`."""
        dt_s = ap.prepare(e)
        flying = dt_s is not None  # else motors off or idle
        operands = self._operands(ap)[:7]  # actuator_frame's: up to the estimator state
        size = actuator_frame(
            self._out,
            self._scratch,
            sequence,
            *self._ids,
            time_us,
            flying,
            True if flying else ap.last_command.armed,
            *operands,
            ap.yaw_rate_ff if flying else 0.0,
            dt_s if flying else 0.0,
            ap.commander.landed if flying else False,
        )
        if flying:
            ap.outputs_in_control()
        return size
