"""Starting the next episode in the air, the autopilots flying on: no reboot, no takeoff
(kinds with `AutopilotFleet.resets_in_air`, e.g. px4, whose restart costs seconds).

The caller (the env's session backend) holds the lockstep with every vehicle hovering slowly
under a zero velocity setpoint that its client keeps streaming. `reset_in_air` then:

1. asks the fleet (`in_air_refusal`: armed, offboard, no failsafe, in the air, slow, level,
   estimate following) and reads what each autopilot estimates of its vehicle
   (`AutopilotFleet.estimates`: position, velocity, tilt);
2. resets the simulation as a session reset does (the layout drawn from the seed, time back
   to 0, sensor noise re-seeded) and places every vehicle `altitude_m` above its spawn in the
   state its autopilot estimates: its estimated attitude and velocity, the rotor speeds it
   flew with;
3. gives every sensor suite the jump as its measured position offset (new offset = old offset
   + old position - new position, `Lockstep.reset_simulation(continuous=True)`), moved onto
   the autopilot's own position estimate: GPS, barometer and HIL ground truth go on without a
   jump the estimator could see, so there is no estimator offset to converge (the thesis's
   teleport problem), while observations and rewards keep reading the simulation's truth;
4. runs `settle_s` of simulated time (the same every episode: the controllers' integrators
   settle under the zero setpoint) and asks the fleet again.

Why the estimated state and not the true one: an estimator cannot be reset without a reboot,
and what it got wrong in the last episode would carry into the next. PX4's EKF2, after a
manoeuvre, holds a tilt error of a few tenths of a degree and a velocity error of 5-9 cm/s
that take ~10 s to decay, while its controller flies the vehicle along with them: started from
the true state, consecutive episodes' first seconds differed by up to 6 cm; started where the
estimate is (which the sensors then confirm), the estimate and the truth agree within ~1 cm/s
at the episode's start and the first seconds within 3 cm (`tests/test_in_air_reset.py`). An
estimate further from the truth than `MAX_TILT_CORRECTION_RAD` or `MAX_VELOCITY_CORRECTION_M_S`
is not placed (refused).
The yaw is the estimate's too (within `MAX_YAW_CORRECTION_RAD` of the truth, which the
magnetometer then confirms): placed at the true yaw, the estimator's yaw error of the moment
carried into the next episode, whose first second turned by a different amount each time.
Rotor speeds carry over because a thrust step would show in the accelerometer. A vehicle keeps
the heading it flew with (an env's offboard setpoints hold the spawn heading), so an episode
whose spawn yaw differs from it by more than `MAX_YAW_ERROR_RAD` is refused. The
measured offset is bounded (`sensors.suite.MAX_POSITION_OFFSET_M`, see there why); past it
the reset is refused too.
A refusal returns the reason, and the caller resets another way (restarts the autopilots).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from sitl_bridge.frames import quat_from_euler_t, quat_ned_frd_to_enu_flu_t, wrap_pi, yaw_ned_to_enu

MAX_YAW_ERROR_RAD = math.radians(5.0)
"""Largest difference between the yaw a vehicle keeps and its spawn yaw."""
MAX_TILT_CORRECTION_RAD = math.radians(2.0)
MAX_YAW_CORRECTION_RAD = math.radians(3.0)
MAX_VELOCITY_CORRECTION_M_S = 0.15
"""The most the placement may differ from the true tilt, yaw and velocity (PX4 after a manoeuvre:
~0.3 deg, <= 0.09 m/s); a larger estimate error is not placed (a report read out of date, or an
estimator that is not following): refused, the caller restarts."""


@dataclass(frozen=True)
class Estimate:
    """What an autopilot estimates of its vehicle, against what its sensors measure."""

    position_error_ned_m: tuple[float, float, float]
    """Measured position (the truth plus the sensors' offset) minus the estimate (m, NED)."""
    velocity_ned_m_s: tuple[float, float, float]
    roll_pitch_rad: tuple[float, float]
    """Estimated roll and pitch (NED/FRD Euler angles)."""
    yaw_rad: float | None = None
    """Estimated yaw (NED/FRD Euler angle); None: not reported, the truth's is kept."""


def reset_in_air(fleet: Any, lockstep: Any, seed: int | None, sensor_seeds: Sequence[int | None] | None,
                 altitude_m: float, settle_s: float) -> str:
    """Held, with the runner off the lockstep (`SimSession.exclusive()`): the next episode in
    the air (module docstring). Returns '' when done, else why not (the simulation may then
    have been reset already)."""
    if not fleet.resets_in_air:
        return f"{type(fleet).__name__} does not reset in the air"
    refusal = fleet.in_air_refusal(lockstep)
    if refusal:
        return f"before the reset: {refusal}"
    sim = lockstep.sim
    count = sim.num_vehicles
    estimates = fleet.estimates(lockstep)
    states = [sim.state(k) for k in range(count)]
    for k, (estimate, state) in enumerate(zip(estimates, states, strict=True)):
        reason = _correction_refusal(estimate, state)
        if reason:
            return f"vehicle {k}: {reason}"
    rotors = [tuple(float(w) for w in state.rotor_speeds_rad_s) for state in states]
    yaws_ned = [float(state.euler_ned_frd_rad[2]) if estimate.yaw_rad is None else float(estimate.yaw_rad)
                for estimate, state in zip(estimates, states, strict=True)]
    yaws = [yaw_ned_to_enu(yaw) for yaw in yaws_ned]

    def place(sim: Any) -> None:
        for k, estimate in enumerate(estimates):
            x, y, z = (float(c) for c in sim.state(k).position_enu_m)  # re-spawned
            roll, pitch = estimate.roll_pitch_rad
            north, east, down = estimate.velocity_ned_m_s
            sim.place_vehicle(k, (x, y, z + altitude_m),
                              quaternion_enu_flu=quat_ned_frd_to_enu_flu_t(quat_from_euler_t(roll, pitch, yaws_ned[k])),
                              velocity_enu_m_s=(east, north, -down), rotor_speeds_rad_s=rotors[k])

    onto_estimates = [tuple(-e for e in estimate.position_error_ned_m) for estimate in estimates]
    if not lockstep.reset_simulation(seed, sensor_seeds, place=place, continuous=True, shifts_ned_m=onto_estimates):
        return "the measured position offset would pass its bound"
    for k in range(count):
        off = abs(wrap_pi(yaws[k] - sim.layout.spawn_yaws_rad[k]))
        if off > MAX_YAW_ERROR_RAD:
            return f"vehicle {k} flies {math.degrees(off):.1f} deg off its spawn yaw"
    lockstep.run_for(settle_s)
    refusal = fleet.in_air_refusal(lockstep)
    return f"after the settle: {refusal}" if refusal else ""


def _correction_refusal(estimate: Estimate, state: Any) -> str:
    """Why `estimate` is too far from the true `state` to place the vehicle there ('' if not)."""
    roll, pitch, _ = (float(a) for a in state.euler_ned_frd_rad)
    tilt = math.hypot(estimate.roll_pitch_rad[0] - roll, estimate.roll_pitch_rad[1] - pitch)
    if not tilt <= MAX_TILT_CORRECTION_RAD:
        return f"estimated tilt {math.degrees(tilt):.1f} deg off the truth"
    if estimate.yaw_rad is not None:
        yaw_off = abs(wrap_pi(float(estimate.yaw_rad) - float(state.euler_ned_frd_rad[2])))
        if not yaw_off <= MAX_YAW_CORRECTION_RAD:
            return f"estimated yaw {math.degrees(yaw_off):.1f} deg off the truth"
    east, north, up = (float(v) for v in state.velocity_enu_m_s)
    off = math.dist(estimate.velocity_ned_m_s, (north, east, -up))
    if not off <= MAX_VELOCITY_CORRECTION_M_S:
        return f"estimated velocity {off:.2f} m/s off the truth"
    return ""
