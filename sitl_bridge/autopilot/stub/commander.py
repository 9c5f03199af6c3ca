"""The stub's commander: arming, modes, land detector, takeoff/hold/land/RTL, offboard failsafe.

Everything runs on simulated time (`time_us` of the sensor frames). Each step the commander
turns the current mode into a `Setpoint` for the position controller and says whether the
motors are off (disarmed), idling (armed on the ground) or flying.

Steady steps (`steady`, `plan`): after a step that flew on in OFFBOARD (no yaw-rate
integration), AUTO.TAKEOFF or AUTO.LOITER with no ground contact (at most one suspected, the land
detector's first stage), the next steps change nothing but the clock as long as the offboard
setpoint stays fresh, the takeoff altitude is not reached and the ground contact test gives what
it gave (no contact; or a suspicion still within its first stage, as after every descent command
while the vehicle gathers speed); after a disarmed step, as long as the home needs no setting. The commander publishes that case as a float64 vector (`plan`) that a
compiled per-step loop tests with `steady_output` (the same predicates `step` uses); any
command, and any step that does not go on so, withdraws it.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass
from enum import Enum

import numpy as np

from sitl_bridge.jit import dual

from .control import Setpoint
from .estimator import Estimate
from .modes import (
    HOLD,
    LAND,
    OFFBOARD,
    RTL,
    TAKEOFF,
    AutoSubMode,
    CommandResult,
    LandedState,
    MainMode,
    custom_mode,
    mode_name,
)
from .params import ParamTable
from .vec import Vec3, quat_yaw, wrap_pi

log = logging.getLogger(__name__)

_NAN = float("nan")
_NAN3 = (_NAN, _NAN, _NAN)
_OFFBOARD_MAIN = OFFBOARD[0]


class Output(Enum):
    """What the motors do this step."""

    OFF = 0     # disarmed: all controls 0
    IDLE = 1    # armed on the ground: idle spin
    FLY = 2     # run the controller


@dataclass
class Home:
    """Home position: set at the first position fix and again on arming (like PX4)."""

    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    position_ned_m: Vec3
    yaw_rad: float


@dataclass
class OffboardSetpoint:
    """Last offboard setpoint (NaN = not controlled), with the simulated time it arrived."""

    position_ned_m: Vec3 = _NAN3
    velocity_ned_m_s: Vec3 = _NAN3
    yaw_rad: float = _NAN
    yaw_rate_rad_s: float = _NAN
    time_us: int = -1


# neither NaN nor infinite; the C function, as it is called several times per step
_finite = math.isfinite

_TAKEOFF_ACCEPT_M = 0.3  # takeoff done when this close to the target altitude

# Commander.plan layout (float64): the setpoint flown (position, velocity, yaw, yaw-rate
# feed-forward with NaN as 0, climb and descent limits), the mode (_PLAN_*), when the offboard
# setpoint arrived (us) and COM_OF_LOSS_T, the takeoff altitude (NED z), LNDMC_Z/XY_VEL_MAX,
# (disarmed) whether the home is still to be set, and since when the land detector suspects a
# ground contact (us, -1: no suspicion) with how long its first stage lasts (us)
(PLAN_POS, PLAN_VEL, PLAN_YAW, PLAN_YAW_RATE_FF, PLAN_UP_MAX, PLAN_DOWN_MAX, _PLAN_MODE, _OFFBOARD_US, _LOSS_S,
 _TAKEOFF_Z, _LND_Z_VEL, _LND_XY_VEL, _HOME_MISSING, _CONTACT_SINCE_US, _CONTACT_STAGE_US) = (
    0, 3, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18)
PLAN_SIZE = 19
_PLAN_OFFBOARD, _PLAN_TAKEOFF, _PLAN_HOLD, _PLAN_OFF = 1.0, 2.0, 3.0, 4.0
# what `steady_output` finds
NOT_STEADY, STEADY_FLY, STEADY_OFF = 0, 1, 2


@dual
def offboard_fresh(time_us: int, sent_us: int, loss_s: float) -> bool:
    """Whether an offboard setpoint sent at `sent_us` (-1: none) still counts at `time_us`."""
    return sent_us >= 0 and time_us - sent_us <= loss_s * 1e6


@dual
def takeoff_reached(z_ned_m: float, target_z_ned_m: float) -> bool:
    """Whether AUTO.TAKEOFF has reached its altitude (then AUTO.LOITER)."""
    return abs(z_ned_m - target_z_ned_m) < _TAKEOFF_ACCEPT_M


@dual
def ground_contact(sp_vz: float, sp_z: float, z: float, vn: float, ve: float, vd: float, vz_limit: float,
                   xy_limit: float) -> bool:
    """The land detector's first stage: a descent commanded (setpoint NED z velocity or
    position) and no vertical or horizontal motion to speak of."""
    descend_commanded = (_finite(sp_vz) and sp_vz > 0.3 * vz_limit) or (_finite(sp_z) and sp_z > z + 0.5)
    # no motion test unless a descent is commanded (the common case in flight: one test)
    return descend_commanded and abs(vd) < 0.6 * vz_limit and math.sqrt(vn * vn + ve * ve) < xy_limit


@dual
def steady_output(plan: np.ndarray, time_us: int, z: float, vn: float, ve: float, vd: float,
                  position_valid: bool) -> int:
    """What `Commander.step` at `time_us` does with this estimate (NED z, velocity, whether the
    position is valid) and the published `plan` (module docstring), changing nothing but its
    clock: STEADY_FLY (flies on with the plan's setpoint) or STEADY_OFF (stays disarmed); or
    NOT_STEADY when it has something to decide (then run it)."""
    mode = plan[_PLAN_MODE]
    if mode == _PLAN_OFF:
        return NOT_STEADY if plan[_HOME_MISSING] != 0.0 and position_valid else STEADY_OFF
    if mode == _PLAN_OFFBOARD and not offboard_fresh(time_us, int(plan[_OFFBOARD_US]), plan[_LOSS_S]):
        return NOT_STEADY
    if mode == _PLAN_TAKEOFF and takeoff_reached(z, plan[_TAKEOFF_Z]):
        return NOT_STEADY
    since = plan[_CONTACT_SINCE_US]
    if ground_contact(plan[PLAN_VEL + 2], plan[PLAN_POS + 2], z, vn, ve, vd, plan[_LND_Z_VEL], plan[_LND_XY_VEL]):
        # steady only while the suspicion goes on in the land detector's first stage (it stays
        # a suspicion: nothing changes); its start and its end are the commander's to decide
        if since < 0.0 or time_us - since >= plan[_CONTACT_STAGE_US]:
            return NOT_STEADY
    elif since >= 0.0:
        return NOT_STEADY  # the suspicion ends: the commander clears it
    return STEADY_FLY


def _same_target(a: OffboardSetpoint, b: OffboardSetpoint) -> bool:
    """Whether two offboard setpoints ask for the same (NaN equals NaN: not controlled)."""
    for x, y in zip((*a.position_ned_m, *a.velocity_ned_m_s, a.yaw_rad, a.yaw_rate_rad_s),
                    (*b.position_ned_m, *b.velocity_ned_m_s, b.yaw_rad, b.yaw_rate_rad_s), strict=True):
        if x != y and (x == x or y == y):
            return False
    return True


def _nan_if_not_finite(x: float) -> float:
    """Setpoint components are finite or NaN (= not controlled); inf would poison the control."""
    x = float(x)
    return x if _finite(x) else _NAN


class Commander:
    """Vehicle state machine; see module docstring. Methods return `CommandResult`."""

    # ground contact / landed: each stage must hold this fraction of LNDMC_TRIG_TIME
    _LAND_STAGE_FRACTION = 1.0 / 3.0
    _RTL_ACCEPT_M = 1.0
    _AIRBORNE_CLIMB_M = 0.3      # climbed this far above the ground point: in the air

    def __init__(self, params: ParamTable) -> None:
        self.params = params
        self.time_us = 0
        self.armed = False
        self.main_mode = int(MainMode.AUTO)
        self.sub_mode = int(AutoSubMode.LOITER)
        self.landed = True
        self.ground_contact = False
        self.maybe_landed = False
        self.home: Home | None = None
        self.offboard = OffboardSetpoint()
        self.estimate: Estimate | None = None
        self.status_texts: deque[tuple[int, str]] = deque(maxlen=32)  # (MAV_SEVERITY, text)
        self.failsafe_active = False
        self._arm_time_us = 0
        self._flown_since_arming = False
        self._landed_since_us = 0
        self._contact_since_us: int | None = None
        self._maybe_since_us: int | None = None
        self._ground_z_m = 0.0
        self._hold_position: Vec3 = _NAN3
        self._yaw_sp = _NAN
        self._takeoff_target: Vec3 = _NAN3
        self._land_xy: tuple[float, float] = (_NAN, _NAN)
        self._rtl_phase = 0
        self._last_setpoint = Setpoint()
        # the OFFBOARD setpoint of the last step and what it was built from: reused while the
        # offboard message and the yaw are the same (a new one only at the 20 Hz resends)
        self._offboard_sp: tuple[OffboardSetpoint, float, Setpoint] | None = None
        self._dt_s = 0.0
        self.plan = np.zeros(PLAN_SIZE)
        """Steady flight, published for compiled loops (module docstring); valid while `steady`."""
        self.steady = False

    # --- state as MAVLink sees it --------------------------------------------------------
    @property
    def custom_mode(self) -> int:
        """PX4 custom_mode of the current mode."""
        return custom_mode(self.main_mode, self.sub_mode)

    @property
    def landed_state(self) -> LandedState:
        """MAV_LANDED_STATE for EXTENDED_SYS_STATE."""
        if not self.armed or self.landed:
            return LandedState.ON_GROUND
        mode = (self.main_mode, self.sub_mode)
        if mode == TAKEOFF:
            return LandedState.TAKEOFF
        if mode == LAND or (mode == RTL and self._rtl_phase == 3):
            return LandedState.LANDING
        return LandedState.IN_AIR

    def _text(self, severity: int, text: str) -> None:
        self.status_texts.append((severity, text))
        log.info("commander: %s", text)

    # --- commands --------------------------------------------------------------------------
    def arm(self) -> CommandResult:
        """Arm if the estimate is good and the mode allows it."""
        if self.armed:
            return CommandResult.ACCEPTED
        e = self.estimate
        if e is None or not e.attitude_valid or not e.position_valid:
            self._text(4, "Arming denied: no position estimate")
            return CommandResult.DENIED
        if (self.main_mode, self.sub_mode) == OFFBOARD and not self._offboard_fresh():
            self._text(4, "Arming denied: no offboard signal")
            return CommandResult.DENIED
        self.steady = False
        self.armed = True
        self._arm_time_us = self.time_us
        self._flown_since_arming = False
        self.landed = True
        self._landed_since_us = self.time_us
        self._ground_z_m = e.position_ned_m[2]
        self._set_home(e)
        self._text(6, "Armed by external command")
        return CommandResult.ACCEPTED

    def place_in_air(self, e: Estimate, home: Home) -> None:
        """After a reboot: the state in which a take-off from `home` ends with the vehicle at
        the estimate `e` (an episode that starts in the air, `StubAutopilot.place_in_air`):
        armed, flown, in the air, AUTO.LOITER holding `e`'s position and heading."""
        self.advance_clock(e.time_us)
        self.estimate = e
        self.home = home
        self.armed = True
        self._arm_time_us = self.time_us
        self._flown_since_arming = True
        self.landed = False
        self.ground_contact = self.maybe_landed = False
        self._contact_since_us = self._maybe_since_us = None
        self._ground_z_m = home.position_ned_m[2]
        self._takeoff_target = e.position_ned_m
        self._enter(HOLD)

    def disarm(self, force: bool = False) -> CommandResult:
        """Disarm; refused in the air unless forced (PX4 param2 = 21196)."""
        if not self.armed:
            return CommandResult.ACCEPTED
        if not self.landed and not force:
            self._text(4, "Disarming denied: not landed")
            return CommandResult.DENIED
        self._disarm("external command")
        return CommandResult.ACCEPTED

    def takeoff(self) -> CommandResult:
        """AUTO.TAKEOFF: climb MIS_TAKEOFF_ALT above home, then AUTO.LOITER."""
        e = self.estimate
        if e is None or not e.position_valid:
            return CommandResult.TEMPORARILY_REJECTED
        if self.home is None:
            self._set_home(e)
        home_z = self.home.position_ned_m[2] if self.home else e.position_ned_m[2]
        target_z = min(home_z - self.params["MIS_TAKEOFF_ALT"], e.position_ned_m[2])
        self._takeoff_target = (e.position_ned_m[0], e.position_ned_m[1], target_z)
        self._yaw_sp = quat_yaw(e.quaternion_ned_frd)
        self._enter(TAKEOFF)
        return CommandResult.ACCEPTED

    def land(self) -> CommandResult:
        """AUTO.LAND at the current horizontal position; disarms after touchdown."""
        e = self.estimate
        if e is None or not e.position_valid:
            return CommandResult.TEMPORARILY_REJECTED
        self._enter(LAND)
        return CommandResult.ACCEPTED

    def hold(self) -> CommandResult:
        """AUTO.LOITER at the stopping point."""
        e = self.estimate
        if e is None or not e.position_valid:
            return CommandResult.TEMPORARILY_REJECTED
        self._enter(HOLD)
        return CommandResult.ACCEPTED

    def return_to_launch(self) -> CommandResult:
        """AUTO.RTL: climb to RTL_RETURN_ALT, fly home, land."""
        e = self.estimate
        if e is None or not e.position_valid or self.home is None:
            return CommandResult.TEMPORARILY_REJECTED
        self._enter(RTL)
        return CommandResult.ACCEPTED

    def reposition(self, position_ned_m: Vec3, yaw_rad: float | None = None) -> CommandResult:
        """Hold (AUTO.LOITER) at a new local position, like PX4's DO_REPOSITION; in the air only."""
        e = self.estimate
        if e is None or not e.position_valid or not self.armed or self.landed:
            return CommandResult.TEMPORARILY_REJECTED
        self._enter(HOLD)
        # A non-finite component keeps the stopping point's (never let inf or NaN reach control).
        self._hold_position = tuple(float(x) if _finite(x) else float(keep)  # type: ignore[assignment]
                                    for x, keep in zip(position_ned_m, self._hold_position, strict=True))
        if yaw_rad is not None and _finite(yaw_rad):
            self._yaw_sp = float(yaw_rad)
        return CommandResult.ACCEPTED

    def set_mode(self, main_mode: int, sub_mode: int) -> CommandResult:
        """DO_SET_MODE with PX4 main/sub modes; RC-only modes are refused (no RC in sim)."""
        if main_mode == MainMode.OFFBOARD:
            if not self._offboard_fresh():
                self._text(4, "Switching to Offboard is currently not possible: no setpoint")
                return CommandResult.TEMPORARILY_REJECTED
            self._enter(OFFBOARD)
            return CommandResult.ACCEPTED
        if main_mode == MainMode.AUTO:
            handlers = {
                AutoSubMode.LOITER: self.hold,
                AutoSubMode.TAKEOFF: self.takeoff,
                AutoSubMode.LAND: self.land,
                AutoSubMode.RTL: self.return_to_launch,
            }
            handler = handlers.get(sub_mode)
            if handler is not None:
                return handler()
            return CommandResult.TEMPORARILY_REJECTED   # READY, MISSION (no mission), ...
        if main_mode in MainMode._value2member_map_:
            # manual / altitude / position / stabilized / acro need RC, which the sim has not
            return CommandResult.TEMPORARILY_REJECTED
        return CommandResult.UNSUPPORTED

    def set_offboard_setpoint(self, position_ned_m: Vec3 = _NAN3, velocity_ned_m_s: Vec3 = _NAN3,
                              yaw_rad: float = _NAN, yaw_rate_rad_s: float = _NAN) -> None:
        """Store an offboard setpoint (NaN components are not controlled), stamped with sim time.
        A resend of the setpoint flown in steady OFFBOARD flight only moves the plan's deadline."""
        new = OffboardSetpoint(
            tuple(_nan_if_not_finite(x) for x in position_ned_m),  # type: ignore[arg-type]
            tuple(_nan_if_not_finite(x) for x in velocity_ned_m_s),  # type: ignore[arg-type]
            _nan_if_not_finite(yaw_rad), _nan_if_not_finite(yaw_rate_rad_s), self.time_us,
        )
        if self.steady and self.plan[_PLAN_MODE] == _PLAN_OFFBOARD and _same_target(new, self.offboard):
            self.plan[_OFFBOARD_US] = new.time_us
        else:
            self.steady = False
        self.offboard = new

    def _offboard_fresh(self) -> bool:
        return offboard_fresh(self.time_us, self.offboard.time_us, self.params.values["COM_OF_LOSS_T"])

    # --- mode entry ------------------------------------------------------------------------
    def _enter(self, mode: tuple[int, int]) -> None:
        e = self.estimate
        self.steady = False
        previous = (self.main_mode, self.sub_mode)
        self.main_mode, self.sub_mode = int(mode[0]), int(mode[1])
        self.failsafe_active = False   # a failsafe sets it again right after entering its mode
        if e is None:
            return
        if mode == HOLD:
            self._hold_position = self._stopping_point(e)
            self._yaw_sp = quat_yaw(e.quaternion_ned_frd)
        elif mode == LAND:
            self._land_xy = self._stopping_point(e)[:2]
            self._yaw_sp = quat_yaw(e.quaternion_ned_frd)
        elif mode == RTL:
            self._rtl_phase = 1
            self._yaw_sp = quat_yaw(e.quaternion_ned_frd)
            self._hold_position = self._stopping_point(e)
        elif mode == OFFBOARD:
            self._yaw_sp = quat_yaw(e.quaternion_ned_frd)
        if mode != previous:
            self._text(6, f"Mode: {mode_name(self.custom_mode)}")

    def _stopping_point(self, e: Estimate) -> Vec3:
        """Where the vehicle comes to rest braking at MPC_ACC_HOR (roughly what PX4 holds)."""
        acc = max(self.params["MPC_ACC_HOR"], 0.5)
        p, v = e.position_ned_m, e.velocity_ned_m_s
        return (p[0] + v[0] * abs(v[0]) / (2 * acc), p[1] + v[1] * abs(v[1]) / (2 * acc),
                p[2] + v[2] * abs(v[2]) / (2 * acc))

    def _set_home(self, e: Estimate) -> None:
        self.home = Home(e.lat_deg, e.lon_deg, e.alt_amsl_m, e.position_ned_m, quat_yaw(e.quaternion_ned_frd))

    def _disarm(self, reason: str) -> None:
        self.steady = False
        self.armed = False
        self.landed = True
        self.ground_contact = self.maybe_landed = False
        self._text(6, f"Disarmed by {reason}")

    # --- per step ----------------------------------------------------------------------------
    def advance_clock(self, time_us: int) -> None:
        """The commander's clock to `time_us` (a step, or a steady-flight step run elsewhere)."""
        self._dt_s = max(0, time_us - self.time_us) * 1e-6 if self.estimate is not None else 0.0
        self.time_us = time_us

    def step(self, e: Estimate, thrust_collective: float) -> tuple[Output, Setpoint]:
        """Advance the state machine to e.time_us; returns what the motors do and the setpoint."""
        self.steady = False
        self.advance_clock(e.time_us)
        self.estimate = e
        if self.home is None and e.position_valid:
            self._set_home(e)
        if not self.armed:
            self.plan[_PLAN_MODE] = _PLAN_OFF
            self.plan[_HOME_MISSING] = 1.0 if self.home is None else 0.0
            self.steady = True
            return Output.OFF, self._last_setpoint
        if self.main_mode == _OFFBOARD_MAIN and not self._offboard_fresh():  # only OFFBOARD can lose its signal
            self._offboard_failsafe()
        sp = self._setpoint(e)
        self._last_setpoint = sp
        if self.landed:
            self._auto_disarm_checks()
            if not self.armed:
                return Output.OFF, sp
            if self._wants_to_climb(e, sp):
                if e.position_ned_m[2] < self._ground_z_m - self._AIRBORNE_CLIMB_M or e.velocity_ned_m_s[2] < -0.5:
                    self.landed = False
                    self._flown_since_arming = True
                    self._contact_since_us = self._maybe_since_us = None
                    self._text(6, "Takeoff detected")
                return Output.FLY, sp
            self._ground_z_m = e.position_ned_m[2]
            return Output.IDLE, sp
        self._land_detector(e, sp, thrust_collective)
        if self.landed:
            self._landed_since_us = self.time_us
            self._ground_z_m = e.position_ned_m[2]
            self._text(6, "Landing detected")
            return Output.IDLE, sp
        if not self.ground_contact:  # no ground contact, at most suspected (maybe_landed neither)
            self._publish(sp)
        return Output.FLY, sp

    def _publish(self, sp: Setpoint) -> None:
        """Publish the steady flight of this step's mode and setpoint, when it is one (`plan`)."""
        mode = (self.main_mode, self.sub_mode)
        plan = self.plan
        if mode == OFFBOARD:
            o = self.offboard
            if not _finite(o.yaw_rad) and _finite(o.yaw_rate_rad_s):
                return  # the yaw setpoint integrates the rate every step
            plan[_PLAN_MODE] = _PLAN_OFFBOARD
        elif mode == HOLD:
            plan[_PLAN_MODE] = _PLAN_HOLD
        elif mode == TAKEOFF:
            plan[_PLAN_MODE] = _PLAN_TAKEOFF
        else:
            return
        p = self.params.values
        yaw_rate_ff = sp.yaw_rate_rad_s
        plan[:] = (*sp.position_ned_m, *sp.velocity_ned_m_s, sp.yaw_rad,
                   0.0 if yaw_rate_ff != yaw_rate_ff else yaw_rate_ff, sp.max_velocity_up_m_s,
                   sp.max_velocity_down_m_s, plan[_PLAN_MODE], self.offboard.time_us, p["COM_OF_LOSS_T"],
                   self._takeoff_target[2], p["LNDMC_Z_VEL_MAX"], p["LNDMC_XY_VEL_MAX"], 0.0,
                   -1.0 if self._contact_since_us is None else self._contact_since_us, self._contact_stage_us())
        self.steady = True

    def _offboard_failsafe(self) -> None:
        if (self.main_mode, self.sub_mode) != OFFBOARD or self._offboard_fresh():
            return
        action = int(self.params["COM_OBL_RC_ACT"])
        self._text(3, "Failsafe: offboard signal lost")
        if action == 7:
            self._disarm("offboard loss failsafe")
        elif action == 3 and self.return_to_launch() is CommandResult.ACCEPTED:
            pass
        elif action in (3, 4):
            self._enter(LAND)
        else:
            # 0-2 fall back to an RC mode; without RC PX4 holds (as does 5 = Hold)
            self._enter(HOLD)
        self.failsafe_active = True

    def _auto_disarm_checks(self) -> None:
        p = self.params.values
        since_landed_s = (self.time_us - self._landed_since_us) * 1e-6
        if self._flown_since_arming:
            if p["COM_DISARM_LAND"] > 0 and since_landed_s >= p["COM_DISARM_LAND"]:
                self._disarm("auto disarm on land")
        elif p["COM_DISARM_PRFLT"] > 0 and (self.time_us - self._arm_time_us) * 1e-6 >= p["COM_DISARM_PRFLT"]:
            self._disarm("auto preflight disarming")

    def _wants_to_climb(self, e: Estimate, sp: Setpoint) -> bool:
        mode = (self.main_mode, self.sub_mode)
        if mode in (LAND, HOLD) or (mode == RTL and self._rtl_phase == 3):
            return False
        vz = sp.velocity_ned_m_s[2]
        pz = sp.position_ned_m[2]
        return (_finite(vz) and vz < -0.2) or (_finite(pz) and pz < e.position_ned_m[2] - 0.3)

    def _contact_stage_us(self) -> float:
        """How long each stage of the land detector lasts (us)."""
        return self.params.values["LNDMC_TRIG_TIME"] * self._LAND_STAGE_FRACTION * 1e6

    def _land_detector(self, e: Estimate, sp: Setpoint, thrust_collective: float) -> None:
        """PX4-like: ground contact (descent commanded, no vertical motion), then maybe landed
        (thrust forced low, still no motion), then landed; each stage a third of LNDMC_TRIG_TIME."""
        p = self.params.values
        stage_us = self._contact_stage_us()
        v = e.velocity_ned_m_s
        if not ground_contact(sp.velocity_ned_m_s[2], sp.position_ned_m[2], e.position_ned_m[2], v[0], v[1], v[2],
                              p["LNDMC_Z_VEL_MAX"], p["LNDMC_XY_VEL_MAX"]):
            self.ground_contact = self.maybe_landed = False
            self._contact_since_us = self._maybe_since_us = None
            return
        if self._contact_since_us is None:
            self._contact_since_us = self.time_us
        self.ground_contact = self.time_us - self._contact_since_us >= stage_us
        if not self.ground_contact:
            return
        if self._maybe_since_us is None:
            self._maybe_since_us = self.time_us
        self.maybe_landed = True
        if self.time_us - self._maybe_since_us >= 2 * stage_us:
            self.landed = True
            self.ground_contact = self.maybe_landed = False
            self._contact_since_us = self._maybe_since_us = None

    # --- setpoints per mode ----------------------------------------------------------------------
    def _setpoint(self, e: Estimate) -> Setpoint:
        mode = (self.main_mode, self.sub_mode)
        p = self.params.values
        if mode == OFFBOARD:
            o = self.offboard
            if _finite(o.yaw_rad):
                self._yaw_sp = o.yaw_rad
            elif _finite(o.yaw_rate_rad_s):
                self._yaw_sp = wrap_pi(self._yaw_sp + o.yaw_rate_rad_s * self._dt_s)
            cached = self._offboard_sp
            if cached is not None and cached[0] is o and cached[1] == self._yaw_sp:
                return cached[2]
            sp = Setpoint(o.position_ned_m, o.velocity_ned_m_s, self._yaw_sp,
                          o.yaw_rate_rad_s if _finite(o.yaw_rate_rad_s) and not _finite(o.yaw_rad) else _NAN)
            self._offboard_sp = (o, self._yaw_sp, sp)
            return sp
        if mode == TAKEOFF:
            t = self._takeoff_target
            if takeoff_reached(e.position_ned_m[2], t[2]) and not self.landed:
                self._enter(HOLD)
                self._hold_position = t
                return Setpoint(t, _NAN3, self._yaw_sp)
            return Setpoint(t, _NAN3, self._yaw_sp, max_velocity_up_m_s=p["MPC_TKO_SPEED"])
        if mode == LAND:
            return Setpoint((self._land_xy[0], self._land_xy[1], _NAN), (_NAN, _NAN, self._land_speed(e)),
                            self._yaw_sp)
        if mode == RTL:
            return self._rtl_setpoint(e)
        return Setpoint(self._hold_position, _NAN3, self._yaw_sp)

    def _land_speed(self, e: Estimate) -> float:
        """MPC_LAND_SPEED near the ground, faster (up to MPC_Z_VEL_MAX_DN) above MPC_LAND_ALT2."""
        p = self.params.values
        home_z = self.home.position_ned_m[2] if self.home else self._ground_z_m
        height = home_z - e.position_ned_m[2]
        slow, fast = p["MPC_LAND_SPEED"], max(p["MPC_Z_VEL_MAX_DN"], p["MPC_LAND_SPEED"])
        alt1, alt2 = p["MPC_LAND_ALT1"], p["MPC_LAND_ALT2"]
        if height <= alt2:
            return slow
        if height >= alt1 or alt1 <= alt2:
            return fast
        return slow + (fast - slow) * (height - alt2) / (alt1 - alt2)

    def _rtl_setpoint(self, e: Estimate) -> Setpoint:
        assert self.home is not None
        home = self.home.position_ned_m
        return_z = min(home[2] - self.params["RTL_RETURN_ALT"], e.position_ned_m[2])
        if self._rtl_phase == 1:   # climb
            target = (self._hold_position[0], self._hold_position[1], min(return_z, self._hold_position[2]))
            self._hold_position = target
            if abs(e.position_ned_m[2] - target[2]) < self._RTL_ACCEPT_M:
                self._rtl_phase = 2
            return Setpoint(target, _NAN3, self._yaw_sp)
        if self._rtl_phase == 2:   # fly home at altitude
            target = (home[0], home[1], self._hold_position[2])
            if math.hypot(e.position_ned_m[0] - home[0], e.position_ned_m[1] - home[1]) < self._RTL_ACCEPT_M:
                self._rtl_phase = 3
                self._land_xy = (home[0], home[1])
            return Setpoint(target, _NAN3, self._yaw_sp)
        return Setpoint((self._land_xy[0], self._land_xy[1], _NAN), (_NAN, _NAN, self._land_speed(e)), self._yaw_sp)
