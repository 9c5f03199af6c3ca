"""`Fleet`: several `OffboardClient`s that share one simulation clock and fly together.

Requests go out to every vehicle first and the clock is then advanced until all have answered,
so N vehicles take off, switch mode and fly each leg in the same simulated time as one.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import Future
from typing import Any

import numpy as np

from sitl_bridge.client.actions import ACTION_DURATION_S, ACTION_SPEED_M_S, action_velocity_ned
from sitl_bridge.client.offboard import (
    API_CLIENT_BASE_PORT,
    OffboardClient,
    OffboardClientError,
    SimClock,
    wait_until,
)


class Fleet:
    """One `OffboardClient` per vehicle instance, all on the same clock (a `SimSession`)."""

    def __init__(self, instances: Sequence[int], *, clock: SimClock,
                 host: str = "127.0.0.1", base_port: int = API_CLIENT_BASE_PORT,
                 urls: Sequence[str] | None = None) -> None:
        self.clock = clock
        if urls is not None and len(urls) != len(instances):
            raise OffboardClientError(f"{len(urls)} URLs for {len(instances)} vehicles")
        self.clients = [
            OffboardClient(i, clock=clock, host=host, base_port=base_port,
                           url=None if urls is None else urls[k])
            for k, i in enumerate(instances)
        ]

    @classmethod
    def for_session(cls, session: Any) -> Fleet:
        """One client per vehicle of a `SimSession` (its instances, API URLs and clock)."""
        return cls(session.instances, clock=session, urls=session.api_urls)

    @classmethod
    def of(cls, clients: Sequence[OffboardClient], *, clock: SimClock) -> Fleet:
        """A fleet of clients that already exist (and may be connected); they must share `clock`."""
        fleet = cls((), clock=clock)
        fleet.clients = list(clients)
        return fleet

    def __len__(self) -> int:
        return len(self.clients)

    def __getitem__(self, index: int) -> OffboardClient:
        return self.clients[index]

    # -- lifecycle --------------------------------------------------------------------
    def connect(self, timeout_s: float = 30.0) -> Fleet:
        try:
            for client in self.clients:
                client.connect(timeout_s)
        except BaseException:
            self.close()
            raise
        return self

    def close(self) -> None:
        for client in self.clients:
            client.close()

    def __enter__(self) -> Fleet:
        return self.connect()

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # -- plumbing ---------------------------------------------------------------------
    def wait_all(self, predicate: Callable[[OffboardClient], bool], what: str,
                 timeout_s: float, poll_s: float = 0.04) -> None:
        """Advance the clock until `predicate` holds for every vehicle."""
        wait_until(lambda: all(predicate(c) for c in self.clients), clock=self.clock,
                   timeout_s=timeout_s, what=f"all vehicles: {what}", poll_s=poll_s)

    def _finish_all(self, futures: Sequence[Future[Any]], what: str, timeout_s: float = 10.0) -> None:
        wait_until(lambda: all(f.done() for f in futures), clock=self.clock, timeout_s=timeout_s,
                   what=f"all vehicles: {what}", poll_s=OffboardClient.COMMAND_POLL_S,
                   min_wall_s=OffboardClient.COMMAND_MIN_WALL_S)
        for client, future in zip(self.clients, futures, strict=True):
            client.finish(future, what)  # already done: only turns errors into exceptions

    # -- flight -----------------------------------------------------------------------
    def wait_healthy(self, timeout_s: float = 60.0) -> None:
        self.wait_all(OffboardClient.is_healthy, "all health flags true", timeout_s)

    def arm(self) -> None:
        self._finish_all([c.submit(c.action.arm) for c in self.clients], "arm")

    def takeoff(self, altitude_m: float, *, timeout_s: float = 30.0, tolerance_m: float = 0.3) -> list[float]:
        """Take off every vehicle to `altitude_m`, wait until all hover there; returns the altitudes."""
        self._finish_all([c.request_takeoff(altitude_m) for c in self.clients], "takeoff")
        self.wait_all(lambda c: c.takeoff_done(altitude_m, tolerance_m),
                      f"hovering at {altitude_m:g} +- {tolerance_m:g} m after takeoff", timeout_s)
        return [c.relative_altitude_m() for c in self.clients]

    def start_offboard(self, timeout_s: float = 5.0, yaws_deg: Sequence[float] | None = None) -> None:
        """Every vehicle in OFFBOARD at zero velocity, holding its heading in `yaws_deg` (NED,
        degrees; default: each one's heading as telemetry reports it now)."""
        yaws = list(yaws_deg) if yaws_deg is not None else [None] * len(self.clients)
        self._finish_all([c.request_offboard(yaw) for c, yaw in zip(self.clients, yaws, strict=True)],
                         "start offboard")
        self.wait_all(lambda c: c.flight_mode() == "OFFBOARD", "flight mode OFFBOARD", timeout_s)

    def fly(self, velocities_ned_m_s: Sequence[Sequence[float] | np.ndarray], duration_s: float,
            yaws_deg: Sequence[float] | None = None) -> None:
        """Give each vehicle its velocity (and heading `yaws_deg`, NED degrees, when given; else
        each keeps the one it holds), then advance exactly `duration_s` simulated seconds."""
        if len(velocities_ned_m_s) != len(self.clients):
            raise OffboardClientError(
                f"fly: expected {len(self.clients)} velocities, got {len(velocities_ned_m_s)}")
        yaws = list(yaws_deg) if yaws_deg is not None else [None] * len(self.clients)
        if len(yaws) != len(self.clients):
            raise OffboardClientError(f"fly: expected {len(self.clients)} yaws, got {len(yaws)}")
        for client, velocity, yaw in zip(self.clients, velocities_ned_m_s, yaws, strict=True):
            client.set_velocity_ned(velocity, yaw)
        # with headings, each delivery is (north, east, down, yaw rad): a new heading at an
        # unchanged velocity must arrive too before time resumes
        self.clock.deliver_setpoints({c.instance: c.commanded_setpoint_ned(with_yaw=yaws_deg is not None)
                                      for c in self.clients})
        self.clock.run_for(duration_s)

    def fly_actions(self, actions: Sequence[int], *, goals_ned_m: Sequence[Sequence[float] | None] | None = None,
                    speed_m_s: float = ACTION_SPEED_M_S,
                    duration_s: float = ACTION_DURATION_S) -> list[np.ndarray]:
        """One thesis action per vehicle, flown simultaneously; returns the commanded velocities."""
        goals = goals_ned_m if goals_ned_m is not None else [None] * len(self.clients)
        velocities = [
            action_velocity_ned(a, position_ned_m=c.position_ned_m(), goal_ned_m=g, speed_m_s=speed_m_s)
            for c, a, g in zip(self.clients, actions, goals, strict=True)
        ]
        self.fly(velocities, duration_s)
        return velocities

    def hold(self, timeout_s: float = 5.0) -> None:
        self._finish_all([c.request_hold() for c in self.clients], "hold")
        self.wait_all(lambda c: c.flight_mode() == "HOLD", "flight mode HOLD", timeout_s)

    def land(self, timeout_s: float = 60.0) -> None:
        self._finish_all([c.request_land() for c in self.clients], "land")
        self.wait_all(OffboardClient.landed_and_disarmed, "landed and disarmed", timeout_s)
