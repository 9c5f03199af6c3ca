"""StubAutopilot: the stub's brain, free of I/O.

One `update(frame)` per lockstep step turns a SensorFrame into a MotorCommand, the way PX4
turns a HIL_SENSOR into a HIL_ACTUATOR_CONTROLS. The MAVLink API layer and the `direct` env
backend drive it through the commander methods (arm, takeoff, set_velocity_setpoint_ned, ...).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

from sitl_bridge.physics.simulation import MotorCommand

from .commander import Commander, Home, OffboardSetpoint, Output
from .control import AttitudeControl, PositionControl, RateControl, Setpoint, body_z_to_attitude
from .estimator import Estimate, GroundTruthEstimator, SensorEstimator
from .mixer import QuadGeometry, QuadXMixer
from .modes import CommandResult, LandedState, system_id_for
from .params import ParamTable

if TYPE_CHECKING:
    from sitl_bridge.sensors import SensorFrame

_NAN = float("nan")
#: period of the position/velocity loop (the attitude and rate loops run every step); it runs on
#: the step nearest to each period, whatever the physics step, and integrates the time that
#: actually passed (8 ms: every 2nd step at 4 ms, every 4th at 2 ms, every 3rd at 3 ms)
POSITION_CONTROL_PERIOD_US = 8000
_OFF = MotorCommand((0.0, 0.0, 0.0, 0.0), False)
_IDLE = MotorCommand((0.0, 0.0, 0.0, 0.0), True)
_FLY = Output.FLY
_new_command = object.__new__
_set_fields = object.__setattr__


def _armed_command(controls: tuple[float, float, float, float]) -> MotorCommand:
    """MotorCommand(controls, True) without the frozen dataclass's checked __init__ (every step)."""
    command = _new_command(MotorCommand)
    _set_fields(command, "controls", controls)
    _set_fields(command, "armed", True)
    return command


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
        self.last_command: MotorCommand = _OFF
        self.thrust_collective = 0.0
        self.attitude_setpoint: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
        self.steps = 0
        self._last_time_us: int | None = None
        self._position_last_us: int | None = None  # the outer loop's last run

    def reset(self) -> None:
        """Reboot in place, as PX4 after `reboot` on a vehicle whose sensors keep running:
        disarmed in AUTO.LOITER with no home, fresh commander, controllers and estimator (the
        estimate is re-initialised from the next sensor samples with the short warm alignment,
        `SensorEstimator.reset`); parameters are kept (PX4 stores them). The clock is kept too
        (`time_us` until the next update), so the MAVLink API's telemetry never goes back in
        time; the next `update` may come at any time (an in-place simulation reset).

        The same object stays in place, so the HIL client and MAVLink API that refer to it
        carry on. A new StubAutopilot is the cold boot (ALIGN_S).
        """
        time_us = self.commander.time_us
        self.estimator.reset()
        self.commander = Commander(self.params)
        self.commander.time_us = time_us
        self.mixer.saturated = False
        self.position_control = PositionControl(self.params)
        self.attitude_control = AttitudeControl(self.params)
        self.rate_control = RateControl(self.params)
        self.last_command = _OFF
        self.thrust_collective = 0.0
        self.attitude_setpoint = (1.0, 0.0, 0.0, 0.0)
        self._last_time_us = None
        self._position_last_us = None

    # --- lockstep ----------------------------------------------------------------------------
    def update(self, frame: SensorFrame) -> MotorCommand:
        """Estimate, run the commander and the control cascade for one step; motor outputs."""
        est = self.estimator.update(frame)
        time_us = frame.time_us
        last = self._last_time_us
        dt_s = 0.0 if last is None or time_us <= last else (time_us - last) * 1e-6
        self._last_time_us = time_us
        self.steps += 1
        commander = self.commander
        output, sp = commander.step(est, self.thrust_collective)
        if output is not _FLY:
            self.position_control.reset()
            self.rate_control.reset()
            self.thrust_collective = 0.0
            self._position_last_us = None
            self.last_command = _IDLE if output is Output.IDLE else _OFF
            return self.last_command

        last_run = self._position_last_us
        step_us = time_us - last if last is not None else 0
        if (last_run is None or time_us < last_run
                or 2 * (time_us - last_run) >= 2 * POSITION_CONTROL_PERIOD_US - step_us):
            # the outer loop runs at ~125 Hz like PX4's mc_pos_control on EKF2 output
            pos_dt_s = (time_us - last_run) * 1e-6 if last_run is not None and time_us > last_run else dt_s
            self._position_last_us = time_us
            self._outer_loop(est, sp, pos_dt_s)
        yaw_rate_ff = sp.yaw_rate_rad_s
        if yaw_rate_ff != yaw_rate_ff:  # NaN: no feed-forward
            yaw_rate_ff = 0.0
        rate_sp = self.attitude_control.update(est.quaternion_ned_frd, self.attitude_setpoint, yaw_rate_ff)
        mixer = self.mixer
        torque = self.rate_control.update(dt_s, est.angular_velocity_frd_rad_s, rate_sp,
                                          mixer.saturated, commander.landed)
        self.last_command = command = _armed_command(mixer.mix(self.thrust_collective, torque))
        return command

    def _outer_loop(self, est: Estimate, sp: Setpoint, dt_s: float) -> None:
        """Position/velocity control -> collective thrust and attitude setpoint."""
        pc = self.position_control
        thr = pc.update(dt_s, sp, est.position_ned_m, est.velocity_ned_m_s, est.accel_ned_m_s2)
        if self.commander.maybe_landed:
            # PX4 drops the thrust to idle when it suspects a landing: confirms or refutes it
            pc.reset()
            thr = (0.0, 0.0, -self.params["MPC_THR_MIN"])
        yaw = sp.yaw_rad
        if yaw != yaw:
            yaw = est.euler_rad[2]
        self.thrust_collective = math.sqrt(thr[0] * thr[0] + thr[1] * thr[1] + thr[2] * thr[2])
        self.attitude_setpoint = body_z_to_attitude((-thr[0], -thr[1], -thr[2]), yaw)

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
