"""Episodes that start in the air on in-process stubs (`direct`, `stub`): every vehicle placed
hovering `altitude_m` above its spawn, its autopilot in the state a take-off would have left
it in, and no take-off flown.

Why not fly the take-off: it costs most of an episode start (arming after the warm alignment,
~3 s of climb, each ~1200 physics steps) and the learner never sees it. Why a placement
rather than a take-off's state replayed: the stub's state after a take-off is known in closed
form (`StubAutopilot.place_in_air`: the estimate converged at the placed state, armed, in
AUTO.LOITER holding it, home at the spawn, integrators at hover thrust), and a placement
depends on nothing but the episode's seed, so episodes stay reproducible.

The caller then goes on as after a take-off: offboard with a zero velocity setpoint and the
settle of `EPISODE_START.settle_s` (through MAVSDK for `stub`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from sitl_bridge.autopilot.stub.autopilot import StubAutopilot
from sitl_bridge.sensors import SensorSuite


def place_hovering(sim: Any, suites: Sequence[SensorSuite], autopilots: Sequence[StubAutopilot],
                   altitude_m: float, times_us: Sequence[int]) -> None:
    """Right after a reset (vehicles on their spawns, autopilots rebooted): vehicle k hovering
    `altitude_m` above its spawn, level at its spawn yaw, at rest, its rotors at hover speed,
    and autopilot k placed there (`StubAutopilot.place_in_air`) on its clock `times_us[k]`."""
    hover = sim.hover_rotor_speeds_rad_s()
    for k, (suite, autopilot) in enumerate(zip(suites, autopilots, strict=True)):
        spawn = suite.ground_truth(sim.state(k))
        _ = spawn.raw, spawn.lat_e7  # evaluated now, before the vehicle moves
        x, y, z = (float(c) for c in sim.state(k).position_enu_m)
        sim.place_vehicle(k, (x, y, z + altitude_m), sim.layout.spawn_yaws_rad[k], rotor_speeds_rad_s=hover)
        autopilot.place_in_air(spawn, suite.ground_truth(sim.state(k)), hover[0], times_us[k])
