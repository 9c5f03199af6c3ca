"""StubAutopilot: the stub's brain, free of I/O.

One `update(frame)` per lockstep step turns a SensorFrame into a MotorCommand, the way PX4
turns a HIL_SENSOR into a HIL_ACTUATOR_CONTROLS. The MAVLink API layer and the `direct` env
backend drive it through the commander methods (arm, takeoff, set_velocity_setpoint_ned, ...).

Per step: the estimator, then `prepare` (commander, and the position loop at ~125 Hz through
the compiled `outer_loop_kernel`), then the attitude + rate loops and the mixer in one compiled
call (`inner_loop_kernel`, the `inner_loop` function that the fused `direct` loop compiles in
too). The controllers' state lives in their float64 vectors (`sitl_bridge.jit`).

Steady steps (`Commander.steady`): `steady_step` is `prepare`'s flying case and the inner loop
on the commander's published `plan`, for a compiled per-step loop that found STEADY_FLY with
`steady_output` (the fused `direct` loop, the stub's fused HIL step); `flew_steady` then
records the step (flown, or STEADY_OFF: motors off) as `prepare` would have.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from sitl_bridge import frames
from sitl_bridge.jit import dual, kernel
from sitl_bridge.physics.simulation import MotorCommand
from sitl_bridge.physics.state import armed_command

from . import control, mixer, vec
from .commander import (
    PLAN_DOWN_MAX,
    PLAN_POS,
    PLAN_UP_MAX,
    PLAN_VEL,
    PLAN_YAW,
    PLAN_YAW_RATE_FF,
    Commander,
    Home,
    OffboardSetpoint,
    Output,
)
from .control import (
    AttitudeControl,
    PositionControl,
    RateControl,
    Setpoint,
    attitude_control,
    body_z_to_attitude,
    idle_thrust,
    position_control,
    rate_control,
)
from .estimator import (
    GRAVITY_M_S2,
    Estimate,
    GroundTruthEstimator,
    SensorEstimator,
    estimator_imu_step,
)
from .mixer import QuadGeometry, QuadXMixer, mix
from .modes import CommandResult, LandedState, system_id_for
from .params import ParamTable
from .vec import quat_to_euler, quat_yaw

if TYPE_CHECKING:
    from sitl_bridge.sensors import GroundTruth, SensorFrame

_NAN = float("nan")
_WARM = False  # the kernels are loaded in this process (StubAutopilot.warm_up)

#: period of the position/velocity loop (the attitude and rate loops run every step); it runs on
#: the step nearest to each period, whatever the physics step, and integrates the time that
#: actually passed (8 ms: every 2nd step at 4 ms, every 4th at 2 ms, every 3rd at 3 ms)
POSITION_CONTROL_PERIOD_US = 8000
_OFF = MotorCommand((0.0, 0.0, 0.0, 0.0), False)
_IDLE = MotorCommand((0.0, 0.0, 0.0, 0.0), True)
_FLY = Output.FLY


# StubAutopilot.control layout: collective thrust, attitude setpoint (w, x, y, z), motor outputs
_THRUST, _Q_SP, _OUTPUTS = 0, 1, 5
CONTROL_STATE = 9


@dual
def seconds_since(time_us: int, last_us: int) -> float:
    """Seconds from the previous step at `last_us` (-1: none) to `time_us`; 0 when none or not later."""
    return 0.0 if last_us < 0 or time_us <= last_us else (time_us - last_us) * 1e-6


@dual
def position_loop_dt(time_us: int, last_us: int, last_run_us: int, dt_s: float) -> float:
    """The position loop's step (s) when it runs at `time_us`, else -1.0: it runs on the step
    nearest to each POSITION_CONTROL_PERIOD_US after its last run at `last_run_us` (-1: never;
    a clock that went back runs it too), and integrates the time that passed since (`dt_s`, this
    step's, after a reset). `last_us`: the previous step (-1: none)."""
    step_us = time_us - last_us if last_us >= 0 else 0
    if (last_run_us < 0 or time_us < last_run_us
            or 2 * (time_us - last_run_us) >= 2 * POSITION_CONTROL_PERIOD_US - step_us):
        return (time_us - last_run_us) * 1e-6 if last_run_us >= 0 and time_us > last_run_us else dt_s
    return -1.0


@dual
def outer_loop(ctl: np.ndarray, pc_state: np.ndarray, pc_gains: np.ndarray, dt_s: float, psp: tuple, vff: tuple,
               up_max: float, down_max: float, pos: tuple, vel: tuple, acc: tuple, maybe_landed: bool,
               yaw: float) -> None:
    """Position/velocity control -> collective thrust and attitude setpoint (into `ctl`)."""
    thr = position_control(pc_state, pc_gains, dt_s, psp, vff, up_max, down_max, pos, vel, acc)
    if maybe_landed:
        # PX4 drops the thrust to idle when it suspects a landing: confirms or refutes it
        thr = idle_thrust(pc_state, pc_gains)
    ctl[_THRUST] = math.sqrt(thr[0] * thr[0] + thr[1] * thr[1] + thr[2] * thr[2])
    ctl[_Q_SP], ctl[_Q_SP + 1], ctl[_Q_SP + 2], ctl[_Q_SP + 3] = body_z_to_attitude((-thr[0], -thr[1], -thr[2]), yaw)


@kernel(frames, vec, control)
def outer_loop_kernel(ctl: np.ndarray, pc_state: np.ndarray, pc_gains: np.ndarray, dt_s: float, sp0: float,
                      sp1: float, sp2: float, ff0: float, ff1: float, ff2: float, up_max: float, down_max: float,
                      p0: float, p1: float, p2: float, v0: float, v1: float, v2: float, a0: float, a1: float,
                      a2: float, maybe_landed: bool, yaw: float) -> None:
    """`outer_loop`, compiled (plain float arguments: numba types tuples slowly)."""
    outer_loop(ctl, pc_state, pc_gains, dt_s, (sp0, sp1, sp2), (ff0, ff1, ff2), up_max, down_max, (p0, p1, p2),
               (v0, v1, v2), (a0, a1, a2), maybe_landed, yaw)


@dual
def inner_loop(ctl: np.ndarray, att_gains: np.ndarray, rate_state: np.ndarray, rate_gains: np.ndarray,
               mix_constants: np.ndarray, mix_state: np.ndarray, q: tuple, rates: tuple, yaw_rate_ff: float,
               dt_s: float, landed: bool) -> tuple[float, float, float, float]:
    """Attitude P -> body-rate PID -> mixer: the motor outputs (also into `ctl`)."""
    rate_sp = attitude_control(att_gains, q, (ctl[_Q_SP], ctl[_Q_SP + 1], ctl[_Q_SP + 2], ctl[_Q_SP + 3]),
                               yaw_rate_ff)
    torque = rate_control(rate_state, rate_gains, dt_s, rates, rate_sp, mix_state[0] != 0.0, landed)
    u = mix(mix_constants, mix_state, ctl[_THRUST], torque)
    o = _OUTPUTS
    ctl[o], ctl[o + 1], ctl[o + 2], ctl[o + 3] = u
    return u


@kernel(frames, vec, control, mixer)
def inner_loop_kernel(ctl: np.ndarray, att_gains: np.ndarray, rate_state: np.ndarray, rate_gains: np.ndarray,
                      mix_constants: np.ndarray, mix_state: np.ndarray, qw: float, qx: float, qy: float, qz: float,
                      wx: float, wy: float, wz: float, yaw_rate_ff: float, dt_s: float,
                      landed: bool) -> tuple[float, float, float, float]:
    """`inner_loop`, compiled."""
    return inner_loop(ctl, att_gains, rate_state, rate_gains, mix_constants, mix_state, (qw, qx, qy, qz),
                      (wx, wy, wz), yaw_rate_ff, dt_s, landed)


@dual
def steady_step(plan: np.ndarray, ctl: np.ndarray, pc_state: np.ndarray, pc_gains: np.ndarray,
                att_gains: np.ndarray, rate_state: np.ndarray, rate_gains: np.ndarray, mix_constants: np.ndarray,
                mix_state: np.ndarray, q: tuple, rates: tuple, pos: tuple, vel: tuple, acc: tuple, time_us: int,
                last_us: int, last_run_us: int) -> tuple[bool, float, float, float, float]:
    """`prepare`'s flying case on a steady commander's `plan` (its setpoint; no landing
    suspected), then `inner_loop`: (whether the position loop ran, the motor outputs)."""
    dt_s = seconds_since(time_us, last_us)
    pos_dt_s = position_loop_dt(time_us, last_us, last_run_us, dt_s)
    if pos_dt_s >= 0.0:
        yaw = plan[PLAN_YAW]
        if yaw != yaw:
            yaw = quat_to_euler(q)[2]
        outer_loop(ctl, pc_state, pc_gains, pos_dt_s, (plan[PLAN_POS], plan[PLAN_POS + 1], plan[PLAN_POS + 2]),
                   (plan[PLAN_VEL], plan[PLAN_VEL + 1], plan[PLAN_VEL + 2]), plan[PLAN_UP_MAX],
                   plan[PLAN_DOWN_MAX], pos, vel, acc, False, yaw)
    u0, u1, u2, u3 = inner_loop(ctl, att_gains, rate_state, rate_gains, mix_constants, mix_state, q, rates,
                                plan[PLAN_YAW_RATE_FF], dt_s, False)
    return pos_dt_s >= 0.0, u0, u1, u2, u3


class StubAutopilot:
    """A PX4-compatible multicopter autopilot without sockets (see docs/architecture.md).

    instance: vehicle instance i (MAVLink system id 1 + i).
    params: parameter table (PX4 names); a fresh default table when None.
    ground_truth_estimate: use SensorFrame.truth instead of estimating from the sensors
        (faster, noise-free; not what PX4 sees).
    geometry: airframe constants for the mixer (Gazebo Iris by default).
    """

    def __init__(self, instance: int = 0, params: ParamTable | None = None, *,
                 ground_truth_estimate: bool = False, geometry: QuadGeometry | None = None) -> None:
        self.instance = instance
        self.params = params if params is not None else ParamTable()
        if "MAV_SYS_ID" in self.params:
            self.params.set("MAV_SYS_ID", system_id_for(instance))
        self.ground_truth_estimate = ground_truth_estimate
        self.estimator = GroundTruthEstimator() if ground_truth_estimate else SensorEstimator()
        self.commander = Commander(self.params)
        self.mixer = QuadXMixer(geometry)
        self.position_control = PositionControl(self.params)
        self.attitude_control = AttitudeControl(self.params)
        self.rate_control = RateControl(self.params)
        self.control = np.zeros(CONTROL_STATE)
        self.control[_Q_SP] = 1.0
        self._command: MotorCommand | None = _OFF
        self._gains_version = -1
        self._yaw_rate_ff = 0.0
        self.steps = 0
        self._last_time_us: int | None = None
        self._position_last_us: int | None = None  # the outer loop's last run
        self.warm_up()

    def warm_up(self) -> None:
        """Load (or, with a cold cache, compile) the compiled kernels now, on scratch copies of
        the state, so that the first lockstep step answers as fast as the others (numba's
        first use in a process costs about a second)."""
        global _WARM
        if _WARM:
            return
        self.refresh_gains()
        estimator = SensorEstimator()
        estimator_imu_step(estimator.state, estimator.gains, 0.0, 0.0, -GRAVITY_M_S2, 0.0, 0.0, 0.0, True, 0.2, 0.0,
                           0.4, 0.004, 4000)
        ctl, pc = self.control.copy(), self.position_control
        nan3 = (_NAN, _NAN, _NAN)
        zero3 = (0.0, 0.0, 0.0)
        outer_loop_kernel(ctl, pc.state.copy(), pc.gains, 0.004, *zero3, *nan3, _NAN, _NAN, *zero3, *zero3, *zero3,
                          False, 0.0)
        inner_loop_kernel(ctl, self.attitude_control.gains, self.rate_control.state.copy(), self.rate_control.gains,
                          self.mixer.constants, self.mixer.state.copy(), 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.004,
                          False)
        _WARM = True

    def reset(self) -> None:
        """Reboot in place, as PX4 after `reboot` on a vehicle whose sensors keep running:
        disarmed in AUTO.LOITER with no home, fresh commander, controllers and estimator (the
        estimate is re-initialised from the next sensor samples with the short warm alignment,
        `SensorEstimator.reset`); parameters are kept (PX4 stores them). The clock is kept too
        (`time_us` until the next update), so the MAVLink API's telemetry never goes back in
        time; the next `update` may come at any time (an in-place simulation reset).

        The same object stays in place, so the HIL client and MAVLink API that refer to it
        carry on. A new StubAutopilot is the cold boot (ALIGN_S). The controllers are new
        objects with new vectors (a fused loop that holds them takes them again).
        """
        time_us = self.commander.time_us
        self.estimator.reset()
        self.commander = Commander(self.params)
        self.commander.time_us = time_us
        self.mixer.saturated = False
        self.position_control = PositionControl(self.params)
        self.attitude_control = AttitudeControl(self.params)
        self.rate_control = RateControl(self.params)
        self._gains_version = -1
        self._command = _OFF
        self.control[:] = 0.0
        self.control[_Q_SP] = 1.0
        self._last_time_us = None
        self._position_last_us = None

    def place_in_air(self, spawn: GroundTruth, placed: GroundTruth, hover_rotor_speed_rad_s: float,
                     time_us: int) -> None:
        """Right after `reset`, with the vehicle just placed hovering at `placed` (level, at
        rest, its rotors at `hover_rotor_speed_rad_s`): the state a take-off from `spawn` ends
        in, without flying it (an episode that starts in the air). The estimate converged at
        the placed state (`SensorEstimator.place` / `GroundTruthEstimator.place`), armed and
        in the air in AUTO.LOITER holding it, home at the spawn (`Commander.place_in_air`), the
        position loop's integrators at hover thrust and the motors at hover
        (`PositionControl.settle_at_hover`), the rate loop's at rest. `time_us`: the clock of
        the next update (the simulation's time for `direct`; the HIL link's for `stub`)."""
        e = self.estimator.place(spawn, placed, time_us)
        origin = e.origin
        assert origin is not None
        self.commander.place_in_air(e, Home(*origin, (0.0, 0.0, 0.0), quat_yaw(e.quaternion_ned_frd)))
        self.refresh_gains()
        collective = self.mixer.collective_for(hover_rotor_speed_rad_s)
        self.position_control.settle_at_hover(collective)
        self.rate_control.reset()
        c = self.control
        c[_THRUST] = collective
        c[_Q_SP:_Q_SP + 4] = body_z_to_attitude((0.0, 0.0, 1.0), quat_yaw(e.quaternion_ned_frd))
        c[_OUTPUTS:_OUTPUTS + 4] = self.mixer.mix(collective, (0.0, 0.0, 0.0))
        self._command = None  # the outputs are in `control`

    # --- controller state as attributes ------------------------------------------------------
    @property
    def last_command(self) -> MotorCommand:
        """The motor command of the last step."""
        if self._command is None:  # the fused `direct` loop leaves the outputs in `control`
            o = _OUTPUTS
            self._command = armed_command(tuple(self.control[o:o + 4].tolist()))  # type: ignore[arg-type]
        return self._command

    @property
    def thrust_collective(self) -> float:
        """Collective thrust setpoint (fraction of full thrust) of the position loop."""
        return float(self.control[_THRUST])

    @property
    def attitude_setpoint(self) -> tuple[float, float, float, float]:
        """Attitude setpoint (w, x, y, z; NED/FRD) of the position loop."""
        return tuple(self.control[_Q_SP:_Q_SP + 4].tolist())  # type: ignore[return-value]

    @property
    def gains_current(self) -> bool:
        """Whether the gain vectors are those of the current parameters (else `prepare` reloads them)."""
        return self._gains_version == self.params.version

    def refresh_gains(self) -> None:
        """Reload the controllers' gain vectors if a parameter changed (cheap when none did)."""
        if self._gains_version != self.params.version:
            self.position_control.refresh_gains()
            self.attitude_control.refresh_gains()
            self.rate_control.refresh_gains()
            self._gains_version = self.params.version

    # --- lockstep ----------------------------------------------------------------------------
    def update(self, frame: SensorFrame) -> MotorCommand:
        """Estimate, run the commander and the control cascade for one step; motor outputs."""
        est = self.estimator.update(frame)
        dt_s = self.prepare(est)
        if dt_s is None:
            return self._command  # type: ignore[return-value]
        yaw_rate_ff = self._yaw_rate_ff
        qw, qx, qy, qz = est.quaternion_ned_frd
        wx, wy, wz = est.angular_velocity_frd_rad_s
        u = inner_loop_kernel(self.control, self.attitude_control.gains, self.rate_control.state,
                              self.rate_control.gains, self.mixer.constants, self.mixer.state, float(qw), float(qx),
                              float(qy), float(qz), float(wx), float(wy), float(wz), yaw_rate_ff, dt_s,
                              self.commander.landed)
        self._command = command = armed_command(u)
        return command

    @property
    def yaw_rate_ff(self) -> float:
        """The yaw-rate feed-forward (rad/s) of this step's setpoint, for `inner_loop`."""
        return self._yaw_rate_ff

    def outputs_in_control(self) -> None:
        """Record that this step's motor outputs were computed by a caller's own compiled
        `inner_loop` (the fused `direct` loop): `last_command` reads them from `control`."""
        self._command = None

    def clock_us(self) -> tuple[int, int]:
        """(the last step's time, the position loop's last run) in us, -1 for none (`steady_step`)."""
        last, last_run = self._last_time_us, self._position_last_us
        return -1 if last is None else last, -1 if last_run is None else last_run

    def flew_steady(self, time_us: int, outer_ran: bool, flying: bool = True) -> None:
        """Record a steady step that a compiled loop ran, as `prepare` would: flown
        (`steady_output` STEADY_FLY, then `steady_step` with `clock_us`, its outputs left in
        `control`) or, not `flying`, disarmed (STEADY_OFF: nothing to do but the clock)."""
        self.commander.advance_clock(time_us)
        self._last_time_us = time_us
        self.steps += 1
        if flying:
            if outer_ran:
                self._position_last_us = time_us
            self._command = None

    def prepare(self, est: Estimate) -> float | None:
        """The commander and the position loop for this step's estimate. Returns the step (s)
        when the inner loop must run (`inner_loop`, with `yaw_rate_ff`), or None when the
        motors are off or idle (`last_command` is then set)."""
        time_us = est.time_us
        last = self._last_time_us
        last_us = -1 if last is None else last
        dt_s = seconds_since(time_us, last_us)
        self._last_time_us = time_us
        self.steps += 1
        if self._gains_version != self.params.version:
            self.refresh_gains()
        commander = self.commander
        output, sp = commander.step(est, float(self.control[_THRUST]))
        if output is not _FLY:
            self.position_control.reset()
            self.rate_control.reset()
            self.control[_THRUST] = 0.0
            self._position_last_us = None
            self._command = _IDLE if output is Output.IDLE else _OFF
            return None

        last_run = self._position_last_us
        # the outer loop runs at ~125 Hz like PX4's mc_pos_control on EKF2 output
        pos_dt_s = position_loop_dt(time_us, last_us, -1 if last_run is None else last_run, dt_s)
        if pos_dt_s >= 0.0:
            self._position_last_us = time_us
            self._outer_loop(est, sp, pos_dt_s)
        yaw_rate_ff = sp.yaw_rate_rad_s
        if yaw_rate_ff != yaw_rate_ff:  # NaN: no feed-forward
            yaw_rate_ff = 0.0
        self._yaw_rate_ff = float(yaw_rate_ff)
        return dt_s

    def _outer_loop(self, est: Estimate, sp: Setpoint, dt_s: float) -> None:
        """Position/velocity control -> collective thrust and attitude setpoint."""
        yaw = sp.yaw_rad
        if yaw != yaw:
            yaw = est.euler_rad[2]
        pc = self.position_control
        # setpoints are floats (the commander sanitises them), the estimate too
        outer_loop_kernel(self.control, pc.state, pc.gains, dt_s, *sp.position_ned_m, *sp.velocity_ned_m_s,
                          float(sp.max_velocity_up_m_s), float(sp.max_velocity_down_m_s), *est.position_ned_m,
                          *est.velocity_ned_m_s, *est.accel_ned_m_s2, self.commander.maybe_landed, float(yaw))

    # --- commander -----------------------------------------------------------------------------
    def arm(self) -> CommandResult:
        """Arm (needs a position estimate; in OFFBOARD a fresh setpoint)."""
        return self.commander.arm()

    def disarm(self, force: bool = False) -> CommandResult:
        """Disarm; in the air only with force=True."""
        return self.commander.disarm(force)

    def takeoff(self) -> CommandResult:
        """AUTO.TAKEOFF to MIS_TAKEOFF_ALT above home, then AUTO.LOITER."""
        return self.commander.takeoff()

    def land(self) -> CommandResult:
        """AUTO.LAND; auto-disarm COM_DISARM_LAND s after touchdown."""
        return self.commander.land()

    def hold(self) -> CommandResult:
        """AUTO.LOITER (MAVSDK's HOLD)."""
        return self.commander.hold()

    def return_to_launch(self) -> CommandResult:
        """AUTO.RTL."""
        return self.commander.return_to_launch()

    def reposition(self, position_ned_m: Sequence[float], yaw_rad: float | None = None) -> CommandResult:
        """Fly to and hold a local NED position in AUTO.LOITER (DO_REPOSITION); in the air only."""
        return self.commander.reposition(tuple(position_ned_m), yaw_rad)  # type: ignore[arg-type]

    def set_mode(self, main_mode: int, sub_mode: int) -> CommandResult:
        """PX4 main/sub mode switch (DO_SET_MODE params 2 and 3)."""
        return self.commander.set_mode(main_mode, sub_mode)

    def set_velocity_setpoint_ned(self, velocity_ned_m_s: Sequence[float], yaw_rad: float | None = None) -> None:
        """Offboard velocity setpoint (m/s NED); yaw None keeps the current heading."""
        self.commander.set_offboard_setpoint(
            velocity_ned_m_s=tuple(velocity_ned_m_s), yaw_rad=_NAN if yaw_rad is None else yaw_rad)

    def set_position_setpoint_ned(self, position_ned_m: Sequence[float], yaw_rad: float | None = None) -> None:
        """Offboard position setpoint (m NED, local origin); yaw None keeps the current heading."""
        self.commander.set_offboard_setpoint(
            position_ned_m=tuple(position_ned_m), yaw_rad=_NAN if yaw_rad is None else yaw_rad)

    def set_offboard_setpoint(self, position_ned_m: Sequence[float] = (_NAN, _NAN, _NAN),
                              velocity_ned_m_s: Sequence[float] = (_NAN, _NAN, _NAN),
                              yaw_rad: float = _NAN, yaw_rate_rad_s: float = _NAN) -> None:
        """General offboard setpoint as SET_POSITION_TARGET_LOCAL_NED carries it (NaN = ignore)."""
        self.commander.set_offboard_setpoint(tuple(position_ned_m), tuple(velocity_ned_m_s), yaw_rad, yaw_rate_rad_s)

    # --- state ---------------------------------------------------------------------------------
    @property
    def time_us(self) -> int:
        """Simulated time of the last update (us)."""
        return self.commander.time_us

    @property
    def armed(self) -> bool:
        return self.commander.armed

    @property
    def custom_mode(self) -> int:
        """PX4 custom_mode for HEARTBEAT."""
        return self.commander.custom_mode

    @property
    def landed_state(self) -> LandedState:
        return self.commander.landed_state

    @property
    def estimate(self) -> Estimate:
        return self.estimator.estimate

    @property
    def home(self) -> Home | None:
        return self.commander.home

    @property
    def offboard_setpoint(self) -> OffboardSetpoint:
        """The last offboard setpoint received (NaN = not controlled; `time_us` = when, -1 =
        none yet). Read it, do not modify it."""
        return self.commander.offboard
