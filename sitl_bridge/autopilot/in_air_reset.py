"""Starting the next episode in the air, the autopilots flying on: no reboot, no takeoff
(kinds with `AutopilotFleet.resets_in_air`, e.g. px4, whose restart costs seconds).

The caller (the env's session backend) holds the lockstep with every vehicle hovering slowly
under a zero velocity setpoint that its client keeps streaming. `reset_in_air` then:

1. asks the fleet (`in_air_refusal`: armed, offboard, no failsafe, in the air, slow, level,
   estimate following);
2. resets the simulation as a session reset does (the layout drawn from the seed, time back
   to 0, sensor noise re-seeded) and places every vehicle `altitude_m` above its spawn with
   the attitude and rotor speeds it flew with, at rest (velocity zeroed, already slow);
3. gives every sensor suite the jump as its measured position offset (new offset = old offset
   + old position - new position, `Lockstep.reset_simulation(continuous=True)`): GPS,
   barometer and HIL ground truth go on continuously, so the autopilot's estimator never sees
   a jump and there is no estimator offset to converge (the thesis's teleport problem), while
   observations and rewards keep reading the simulation's truth;
4. runs `settle_s` of simulated time (the same every episode: the controllers' integrators
   settle under the zero setpoint) and asks the fleet again.

Attitude and rotor speeds carry over because a tilt or yaw the gyro never saw would stay in
the autopilot's attitude estimate (and its magnetometer would disagree): the vehicle keeps
the yaw it flew with, so an episode whose spawn yaw differs by more than
`MAX_YAW_ERROR_RAD` is refused. The measured offset is bounded
(`sensors.suite.MAX_POSITION_OFFSET_M`, see there why); past it the reset is refused too.
A refusal returns the reason, and the caller resets another way (restarts the autopilots).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from sitl_bridge.frames import wrap_pi, yaw_ned_to_enu

MAX_YAW_ERROR_RAD = math.radians(5.0)
"""Largest difference between the yaw a vehicle keeps and its spawn yaw."""


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
    states = [sim.state(k) for k in range(count)]
    attitudes = [tuple(float(c) for c in state.quaternion_enu_flu) for state in states]
    rotors = [tuple(float(w) for w in state.rotor_speeds_rad_s) for state in states]
    yaws = [yaw_ned_to_enu(float(state.euler_ned_frd_rad[2])) for state in states]

    def place(sim: Any) -> None:
        for k in range(count):
            x, y, z = (float(c) for c in sim.state(k).position_enu_m)  # re-spawned, at rest
            sim.place_vehicle(k, (x, y, z + altitude_m), quaternion_enu_flu=attitudes[k],
                              rotor_speeds_rad_s=rotors[k])

    if not lockstep.reset_simulation(seed, sensor_seeds, place=place, continuous=True):
        return "the measured position offset would pass its bound"
    for k in range(count):
        off = abs(wrap_pi(yaws[k] - sim.layout.spawn_yaws_rad[k]))
        if off > MAX_YAW_ERROR_RAD:
            return f"vehicle {k} flies {math.degrees(off):.1f} deg off its spawn yaw"
    lockstep.run_for(settle_s)
    refusal = fleet.in_air_refusal(lockstep)
    return f"after the settle: {refusal}" if refusal else ""
