"""When a real PX4 may fly on into the next episode (`autopilot.in_air_reset`) instead of
being restarted: the checks of `Px4SitlFleet.in_air_refusal`, on what PX4 reports and on the
simulation's truth.

PX4 keeps its whole state across such a reset (estimator, controllers, commander, params), so
it must be in the same clean flying state at every episode start: armed, in OFFBOARD, no
failsafe (PX4 then reports MAV_STATE_CRITICAL or worse and leaves OFFBOARD), in the air (not
landed or touching down after a ground contact), slow and nearly level, and its estimate must
agree with what its sensors measure (the truth plus the sensors' measured position offset).
Anything else (a crash, a tumble, a failsafe, a diverged estimator) is cured by the restart.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from sitl_bridge import mavlink
from sitl_bridge.autopilot.modes import OFFBOARD, mode_name, split_custom_mode
from sitl_bridge.autopilot.px4.observer import Px4Observation
from sitl_bridge.physics.state import VehicleState


@dataclass(frozen=True)
class InAirLimits:
    """How clean the flight must be (truth, and PX4's estimate against the measured state)."""

    min_height_m: float = 0.3
    """Above the ground (truth, the body centre): lower is a touchdown or a crash."""
    max_speed_m_s: float = 0.3
    max_tilt_deg: float = 10.0
    max_rate_rad_s: float = 0.5
    max_position_error_m: float = 0.5
    """PX4's local position estimate against the measured position (both in PX4's frame)."""
    max_velocity_error_m_s: float = 0.3


IN_AIR_LIMITS = InAirLimits()

_IN_AIR = mavlink.dialect.MAV_LANDED_STATE_IN_AIR
_FLYING_STATUS = (mavlink.dialect.MAV_STATE_ACTIVE,)


def refusal(obs: Px4Observation, state: VehicleState, position_error_m: float,
            velocity_error_m_s: float, limits: InAirLimits = IN_AIR_LIMITS) -> str:
    """Why this vehicle cannot fly on into the next episode ('' when it can)."""
    if not obs.heartbeat:
        return "no heartbeat"
    if not obs.armed:
        return "disarmed"
    if split_custom_mode(obs.custom_mode) != OFFBOARD:
        return f"not in offboard (custom_mode {obs.custom_mode})"
    if obs.system_status not in _FLYING_STATUS:
        return f"system status {obs.system_status} (failsafe or emergency)"
    if obs.landed_state != _IN_AIR:
        return f"landed state {obs.landed_state}, not in the air"
    height = float(state.position_enu_m[2])
    if height < limits.min_height_m:
        return f"height {height:.2f} m"
    speed = float(math.hypot(*state.velocity_enu_m_s))
    if speed > limits.max_speed_m_s:
        return f"moving at {speed:.2f} m/s"
    roll, pitch, _ = (float(a) for a in state.euler_ned_frd_rad)
    tilt = math.degrees(math.acos(max(-1.0, min(1.0, math.cos(roll) * math.cos(pitch)))))
    if tilt > limits.max_tilt_deg:
        return f"tilted {tilt:.1f} deg"
    rate = float(math.hypot(*state.angular_velocity_flu_rad_s))
    if rate > limits.max_rate_rad_s:
        return f"turning at {rate:.2f} rad/s"
    if not position_error_m <= limits.max_position_error_m:
        return f"estimate {position_error_m:.2f} m off the measured position"
    if not velocity_error_m_s <= limits.max_velocity_error_m_s:
        return f"estimate {velocity_error_m_s:.2f} m/s off the velocity"
    return ""


def _enum_name(enum: str, value: int) -> str:
    entry = mavlink.dialect.enums.get(enum, {}).get(value)
    return entry.name.removeprefix(enum + "_") if entry is not None else str(value)


def describe(obs: Px4Observation, state: VehicleState, estimated_height_m: float | None, now_wall_s: float) -> str:
    """What a refusal rests on, to tell the next odd one apart: truth and PX4's estimate of the
    height, what PX4 last reported (landed state, mode, armed, status) and how old each of its
    reports is (wall seconds since it arrived)."""
    estimate = f"{estimated_height_m:.2f} m" if estimated_height_m is not None else "none"
    ages = ", ".join(f"{name} {now_wall_s - at:.2f}" for name, at in sorted(obs.received_wall_s.items()))
    return (f"height truth {float(state.position_enu_m[2]):.2f} m, PX4 estimate {estimate}; "
            f"landed state {_enum_name('MAV_LANDED_STATE', obs.landed_state)}, mode {mode_name(obs.custom_mode)}, "
            f"{'armed' if obs.armed else 'disarmed'}, status {_enum_name('MAV_STATE', obs.system_status)}; "
            f"report ages (wall s): {ages or 'none received'}")
