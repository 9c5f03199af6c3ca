"""`stub` and `px4` backends: the full protocol path through `SimSession` and MAVSDK.

simulator -> HIL link (TCP) -> autopilot (in-process stub, or real PX4) -> MAVLink API (UDP)
-> MAVSDK (`Fleet` of `OffboardClient`s) -> this backend. Every command of an episode goes
through MAVSDK exactly as a user's script would send it; ground truth for observations and
rewards is read from the simulation while it is held.

Episode start (see `base`): the same sequence as `direct`, through MAVSDK: arm (retried every
`ARM_POLL_S` while the autopilot denies it), takeoff to the start altitude, wait until hovering
there in HOLD, offboard with a zero-velocity setpoint, settle.

Reset between episodes:
* `stub`: in place, on the same ports and MAVSDK connections: `SimSession.reset(seed)`
  re-spawns the simulation with the episode's seed (simulated time back to 0, as `direct`),
  re-seeds the sensor noise and reboots every stub (`StubVehicle.reset`: disarmed, fresh
  estimator with the short warm alignment, as `direct`'s `StubAutopilot.reset`), while the
  HIL link keeps the stubs' clock counting up (their stream schedules, the lockstep's answer
  matching and MAVSDK all see monotonic time).
* `px4`: PX4's estimator cannot be teleported (the thesis's position jump), so the session is
  restarted: PX4 processes, links and MAVSDK clients, on the same instances.

Collisions come from the session's collision log (`SimSession.take_collisions`), each
physics step's exactly once; a new setpoint reaches in-process stubs before the first step
of its span (`SimSession.deliver_pending_commands`), as in `direct`.
"""

from __future__ import annotations

import contextlib
import tempfile
from collections.abc import Sequence

import numpy as np

from sitl_bridge.client import Fleet, OffboardClientError
from sitl_bridge.envs.backends.base import (
    ARM_POLL_S,
    SETTLE_S,
    STARTUP_TIMEOUT_S,
    TAKEOFF_TOLERANCE_M,
    BackendError,
    Snapshot,
    check_estimator,
)
from sitl_bridge.sensors.lidar import Lidar
from sitl_bridge.session import SessionError, SimSession
from sitl_bridge.world import World

"""Wall seconds a velocity setpoint may take from MAVSDK to an in-process stub."""


class SessionBackend:
    """A `SimSession` with a MAVSDK `Fleet`, flown through the Backend API."""

    def __init__(self, world: World, *, autopilot: str, start_altitude_m: float,
                 speed_factor: float = 0.0, instance_base: int = 0,
                 px4_bin: str | None = None, gui: bool = False, estimator: str = "sensors") -> None:
        if autopilot not in ("stub", "px4"):
            raise ValueError(f"SessionBackend runs 'stub' or 'px4', got {autopilot!r}")
        self.estimator = check_estimator(estimator, autopilot)
        self.name = autopilot
        self.world = world
        self.num_drones = world.num_vehicles
        self.start_altitude_m = float(start_altitude_m)
        # PX4 keeps its working directories and logs here across restarts; removed on close.
        self._run_dir = tempfile.TemporaryDirectory(prefix="sitl-bridge-env-") if autopilot == "px4" else None
        self._options = dict(autopilot=autopilot, speed_factor=speed_factor,
                             instance_base=instance_base, px4_bin=px4_bin, gui=gui,
                             run_dir=self._run_dir.name if self._run_dir is not None else None,
                             stub_ground_truth=estimator == "ground_truth")
        self.session: SimSession | None = None
        self.fleet: Fleet | None = None
        self.lidar: Lidar | None = None
        self._collided = [False] * self.num_drones
        self._episode_start_us = 0
        self._closed = False

    # -- Backend API --------------------------------------------------------------------
    def reset(self, seed: int | None = None) -> Snapshot:
        seed = 0 if seed is None else int(seed)
        if self.session is not None and self.name == "px4":
            self._stop()  # PX4: restart rather than teleport its estimator
        if self.session is None:
            self._start(seed)
        session = self._session()
        if self.name == "stub":
            # Also right after a start: connecting let time run, and every episode must begin
            # from the same state as `direct`'s (rebooted autopilot, freshly seeded sensors).
            session.reset(seed)
            assert self.lidar is not None
            self.lidar.reset()
        # A PX4 just started on the episode's layout (drawn from `seed` by SimSession).
        self._episode_start_us = session.time_us
        self._hover_start()
        session.take_collisions()  # the episode start's do not count
        self._collided = [False] * self.num_drones
        return self._snapshot()

    def fly(self, velocities_ned_m_s: Sequence[np.ndarray], duration_s: float) -> Snapshot:
        fleet = self._fleet()
        session = self._session()
        if len(velocities_ned_m_s) != self.num_drones:
            raise ValueError(f"expected {self.num_drones} velocities, got {len(velocities_ned_m_s)}")
        session.take_collisions()  # none since the last call's end, which was held
        try:
            # the fleet makes every setpoint reach its stub before time resumes, as in `direct`
            fleet.fly([np.asarray(v, dtype=float) for v in velocities_ned_m_s], duration_s)
        except SessionError as exc:
            raise BackendError(f"{self.name}: {exc}") from None
        self._collided = [False] * self.num_drones
        for collision in session.take_collisions():
            self._collided[collision.vehicle] = True
        return self._snapshot()

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._stop()
            if self._run_dir is not None:
                self._run_dir.cleanup()

    # -- lifecycle ------------------------------------------------------------------------------
    def _session(self) -> SimSession:
        if self.session is None:
            raise BackendError(f"{self.name}: not started (call reset())")
        return self.session

    def _fleet(self) -> Fleet:
        if self.fleet is None:
            raise BackendError(f"{self.name}: not started (call reset())")
        return self.fleet

    def _start(self, seed: int) -> None:
        session = SimSession(self.world, seed=seed, **self._options)  # type: ignore[arg-type]
        try:
            session.start()
            self.session = session
            self.fleet = Fleet(session.instances, clock=session).connect()
        except BaseException:
            self.session = session
            self._stop()
            raise
        assert session.sim is not None
        self.lidar = Lidar(session.sim, [v.lidar for v in self.world.vehicles])

    def _stop(self) -> None:
        if self.fleet is not None:
            with contextlib.suppress(Exception):
                self.fleet.close()
            self.fleet = None
        if self.session is not None:
            self.session.close()
            self.session = None
        self.lidar = None

    # -- episode start --------------------------------------------------------------------------
    def _hover_start(self) -> None:
        session, fleet = self._session(), self._fleet()
        waited = 0.0
        while True:
            try:
                fleet.arm()
                break
            except OffboardClientError:
                if waited >= STARTUP_TIMEOUT_S:
                    raise BackendError(f"{self.name}: vehicles never became armable") from None
                session.run_for(ARM_POLL_S)
                waited += ARM_POLL_S
        fleet.takeoff(self.start_altitude_m, timeout_s=STARTUP_TIMEOUT_S,
                      tolerance_m=TAKEOFF_TOLERANCE_M)
        fleet.start_offboard()
        session.run_for(SETTLE_S)

    # -- observation ----------------------------------------------------------------------------
    def _snapshot(self) -> Snapshot:
        session = self._session()
        sim = session.sim
        assert sim is not None and self.lidar is not None
        layout = sim.layout
        return Snapshot(
            time_us=sim.time_us - self._episode_start_us,
            states=tuple(sim.state(i) for i in range(self.num_drones)),
            scans=tuple(self.lidar.scan()),
            collided=tuple(self._collided),
            goals=tuple(layout.goal_of(i) for i in range(self.num_drones)),  # type: ignore[arg-type]
        )
