"""`Px4Fleet`: the PX4 processes of all vehicles of a lockstep, started, connected, made
ready, restarted (or reset in place) between episodes, stopped."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from typing import Any

from sitl_bridge import mavlink
from sitl_bridge.autopilot.px4.observer import Px4Observation
from sitl_bridge.autopilot.px4.process import Px4Autopilot, Px4Config, Px4Died, Px4Error
from sitl_bridge.hil.errors import HilError


class Px4Fleet:
    """PX4 processes for vehicles 0..n-1 of a lockstep (instances `instance_base + i`):
    start, connect to the links, wait until ready, restart between episodes, stop.

    `lockstep` is a `sitl_bridge.hil.Lockstep` whose links are the vehicles' `HilLink`s.
    """

    def __init__(self, config: Px4Config, instances: Sequence[int]) -> None:
        self.autopilots = [Px4Autopilot(config, instance) for instance in instances]
        self.last_ready_wall_s = 0.0
        # true NED position minus PX4's local estimate, when each became ready
        self._origin_offsets: list[tuple[float, float, float] | None] = [None] * len(self.autopilots)

    def start(self) -> None:
        for autopilot in self.autopilots:
            autopilot.start()

    def stop(self) -> None:
        for autopilot in self.autopilots:
            autopilot.stop()

    def check_alive(self) -> None:
        for autopilot in self.autopilots:
            autopilot.check_alive()

    def explain(self, error: BaseException, wait_s: float = 2.0) -> BaseException:
        """Turn a link failure (LinkClosed, LockstepTimeout) into `Px4Died` with the console
        tail when a PX4 process is what died (waiting up to `wait_s` for it to exit);
        otherwise return `error` unchanged. Use as `raise fleet.explain(exc) from exc`."""
        deadline = time.monotonic() + wait_s
        while True:
            for autopilot in self.autopilots:
                if autopilot.returncode is not None:
                    try:
                        autopilot.check_alive()
                    except Px4Died as died:
                        return died
            if time.monotonic() > deadline:
                return error
            time.sleep(0.02)

    def connect(self, links: Sequence[Any], timeout_s: float = 30.0) -> None:
        """Wait until every PX4 connected to its link (checking that none died)."""
        deadline = time.monotonic() + timeout_s
        for autopilot, link in zip(self.autopilots, links, strict=True):
            while not link.accept(0.05):
                autopilot.check_alive()
                if time.monotonic() > deadline:
                    raise Px4Error(
                        f"PX4 instance {autopilot.instance} did not connect to TCP {link.port} "
                        f"within {timeout_s} s; last output:\n{autopilot.tail()}"
                    )

    def wait_ready(self, lockstep: Any, *, timeout_s: float = 120.0, max_sim_s: float = 300.0) -> float:
        """Run the lockstep until every PX4 is observed ready; returns the wall seconds it
        took. Raises Px4Died or Px4Error (with console tails) on failure."""
        start = time.monotonic()
        deadline = start + timeout_s

        def all_ready() -> bool:
            self.check_alive()
            if time.monotonic() > deadline:
                tails = "\n".join(
                    f"--- PX4 instance {a.instance} ({a.observation}):\n{a.tail(15)}" for a in self.autopilots
                )
                raise Px4Error(f"PX4 not ready after {timeout_s} s wall:\n{tails}")
            return all(a.ready and a.observation.position_ned_m is not None for a in self.autopilots)

        try:
            ready = lockstep.run_until(all_ready, max_seconds=max_sim_s, check_every_s=0.2)
        except HilError as exc:
            raise self.explain(exc) from exc
        if not ready:
            raise Px4Error(f"PX4 not ready after {max_sim_s} s of simulated time")
        for index, autopilot in enumerate(self.autopilots):
            self._origin_offsets[index] = self._offset(lockstep, index, autopilot.observation)
        self.last_ready_wall_s = time.monotonic() - start
        return self.last_ready_wall_s

    @staticmethod
    def _offset(lockstep: Any, index: int, obs: Px4Observation) -> tuple[float, float, float]:
        true = lockstep.sim.state(index).position_ned_m
        estimate = obs.position_ned_m or (0.0, 0.0, 0.0)
        return (float(true[0]) - estimate[0], float(true[1]) - estimate[1], float(true[2]) - estimate[2])

    def estimate_error_m(self, lockstep: Any, index: int) -> float:
        """Distance between PX4's position estimate and the truth (in PX4's local frame)."""
        obs = self.autopilots[index].observation
        origin = self._origin_offsets[index]
        if obs.position_ned_m is None or origin is None:
            return float("inf")
        offset = self._offset(lockstep, index, obs)
        return math.dist(offset, origin)

    def reset_in_place(self, lockstep: Any, reset: Callable[[], None] | None = None, *,
                       tolerance_m: float = 0.3,
                       timeout_s: float = 120.0, max_sim_s: float = 120.0) -> float:
        """The alternative to `restart`: keep PX4 running, force-disarm it, `reset()` the
        simulation (default `lockstep.reset_simulation()`: the vehicle jumps back to its spawn) and run until PX4's estimate has
        followed (within `tolerance_m`, nearly at rest) and its pre-arm checks pass again.
        Returns the wall seconds. PX4's clock keeps running forward (the link makes wire time
        monotonic across the reset)."""
        start = time.monotonic()
        deadline = start + timeout_s
        disarm = mavlink.dialect.MAV_CMD_COMPONENT_ARM_DISARM
        for autopilot in self.autopilots:
            autopilot.command(disarm, 0, 21196)  # 21196: force, even in the air

        def disarmed() -> bool:
            self.check_alive()
            return all(not a.poll().armed for a in self.autopilots)

        if not lockstep.run_until(disarmed, max_seconds=10.0, check_every_s=0.02):
            raise Px4Error("PX4 did not disarm for the in-place reset")
        (reset or lockstep.reset_simulation)()
        for autopilot in self.autopilots:
            autopilot.observation.prearm_ok = False
            autopilot.observation.position_ned_m = None

        def converged() -> bool:
            self.check_alive()
            if time.monotonic() > deadline:
                raise Px4Error(f"PX4 estimate did not follow the in-place reset within {timeout_s} s")
            for index, autopilot in enumerate(self.autopilots):
                obs = autopilot.poll()
                if not obs.prearm_ok or obs.velocity_ned_m_s is None:
                    return False
                if self.estimate_error_m(lockstep, index) > tolerance_m:
                    return False
                if math.hypot(*obs.velocity_ned_m_s) > 0.2:
                    return False
            return True

        if not lockstep.run_until(converged, max_seconds=max_sim_s, check_every_s=0.1):
            raise Px4Error(f"PX4 estimate did not follow the in-place reset in {max_sim_s} s simulated")
        return time.monotonic() - start

    def restart(self, lockstep: Any, reset: Callable[[], None] | None = None, *,
                connect_timeout_s: float = 30.0, ready_timeout_s: float = 120.0) -> float:
        """Episode restart: hold, stop every PX4, drop the links, `reset()` the simulation
        (default: `lockstep.reset_simulation()`, physics and sensors), start PX4 again,
        reconnect and wait until ready. Returns restart-to-ready wall seconds."""
        start = time.monotonic()
        lockstep.hold()
        self.stop()
        for link in lockstep.links:
            link.disconnect()
        (reset or lockstep.reset_simulation)()
        self.start()
        self.connect(lockstep.links, connect_timeout_s)
        self.wait_ready(lockstep, timeout_s=ready_timeout_s)
        return time.monotonic() - start

    def __enter__(self) -> Px4Fleet:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
