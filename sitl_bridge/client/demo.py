"""The built-in offboard demo of `sitl-bridge run --demo`: take off, fly the six velocity
directions (1 m/s for 1 s simulated each, then settle at zero velocity), hold, land.

Every vehicle of the fleet flies the same legs at the same time; each leg reports the
commanded displacement next to the one MAVSDK's telemetry saw.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from sitl_bridge.client.actions import (
    ACTION_DURATION_S,
    ACTION_SPEED_M_S,
    Action,
    action_velocity_ned,
)
from sitl_bridge.client.fleet import Fleet

DEMO_ACTIONS = (Action.EAST, Action.WEST, Action.SOUTH, Action.NORTH, Action.UP, Action.DOWN)
"""The six directions, in an order that ends where it started (up before down)."""

SETTLE_S = 2.0
"""Simulated seconds at zero velocity after each leg before the displacement is read."""


@dataclass(frozen=True)
class LegResult:
    """One leg of one vehicle: what was commanded and what telemetry reported (NED, m)."""

    vehicle: int
    action: str
    commanded_ned_m: tuple[float, float, float]
    achieved_ned_m: tuple[float, float, float]

    @property
    def error_m(self) -> float:
        """Distance between commanded and achieved displacement."""
        return float(np.linalg.norm(np.subtract(self.achieved_ned_m, self.commanded_ned_m)))

    def line(self) -> str:
        c, a = self.commanded_ned_m, self.achieved_ned_m
        return (f"vehicle {self.vehicle} {self.action:<5} commanded N{c[0]:+.2f} E{c[1]:+.2f} D{c[2]:+.2f}"
                f"  achieved N{a[0]:+.2f} E{a[1]:+.2f} D{a[2]:+.2f}  error {self.error_m:.2f} m")


def fly_leg(fleet: Fleet, action: Action, *, speed_m_s: float = ACTION_SPEED_M_S,
            duration_s: float = ACTION_DURATION_S, settle_s: float = SETTLE_S) -> list[LegResult]:
    """Fly one direction with every vehicle, settle, and measure each displacement."""
    start = [c.position_ned_m() for c in fleet.clients]
    velocity = action_velocity_ned(action, speed_m_s=speed_m_s)
    fleet.fly([velocity] * len(fleet), duration_s)
    fleet.fly([np.zeros(3)] * len(fleet), settle_s)
    commanded = tuple(float(v) for v in velocity * duration_s)
    return [
        LegResult(c.instance, action.name.lower(), commanded,
                  tuple(float(v) for v in c.position_ned_m() - p0))
        for c, p0 in zip(fleet.clients, start, strict=True)
    ]


def run_demo(fleet: Fleet, *, altitude_m: float = 2.5, report: Callable[[str], None] = print,
             actions: tuple[Action, ...] = DEMO_ACTIONS) -> list[LegResult]:
    """Fly the whole demo with a connected fleet; returns every leg's result."""
    report(f"waiting for health of {len(fleet)} vehicle(s)")
    fleet.wait_healthy()
    report("arming")
    fleet.arm()
    report(f"taking off to {altitude_m:g} m")
    fleet.takeoff(altitude_m)
    for client in fleet.clients:
        report(f"vehicle {client.instance} at {client.relative_altitude_m():.2f} m, mode {client.flight_mode()}")
    fleet.start_offboard()
    report("offboard: flying the six directions")
    results: list[LegResult] = []
    for action in actions:
        for leg in fly_leg(fleet, action):
            report(leg.line())
            results.append(leg)
    fleet.hold()
    report("hold; landing")
    fleet.land()
    report("landed and disarmed")
    return results
