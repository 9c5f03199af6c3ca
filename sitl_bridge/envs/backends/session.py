"""The session backend (`stub`, `px4`, any kind with a session and env support): the full
protocol path through `SimSession` and MAVSDK.

simulator -> HIL link (TCP) -> autopilot (in-process stub, or real PX4) -> MAVLink API (UDP)
-> MAVSDK (`Fleet` of `OffboardClient`s) -> this backend. Every command of an episode goes
through MAVSDK exactly as a user's script would send it; ground truth for observations and
rewards is read from the simulation while it is held.

Episode start (see `base`): the same sequence as `direct`, through MAVSDK: arm (retried every
`EPISODE_START.arm_poll_s` while the autopilot denies it), takeoff to the start altitude, wait
until hovering there in HOLD, offboard with a zero-velocity setpoint, settle.

In-process stubs (`AutopilotFleet.places_in_air`) skip the arming and the take-off unless the
scenario asks for them (`takeoff`): after the in-place reset, `place_in_air` sets every vehicle
hovering at the start altitude and its stub in the state a take-off ends in, then MAVSDK
starts offboard and the settle runs, as after a take-off.

Reset between episodes, as the kind's fleet says (`AutopilotFleet.resets_in_place`):
* in place (`stub`), on the same ports and MAVSDK connections: `SimSession.reset(seed)`
  re-spawns the simulation with the episode's seed (simulated time back to 0, as `direct`),
  re-seeds the sensor noise and reboots every stub (`StubVehicle.reset`: disarmed, fresh
  estimator with the short warm alignment, as `direct`'s `StubAutopilot.reset`), while the
  HIL link keeps the stubs' clock counting up (their stream schedules, the lockstep's answer
  matching and MAVSDK all see monotonic time).
* in the air (`px4`, kinds with `AutopilotFleet.resets_in_air`): PX4 flies on, no reboot, no
  takeoff. The episode's end is held with a zero velocity setpoint until every vehicle is slow
  (`EPISODE_START.in_air_stop_speed_m_s`, as its autopilot estimates it), then
  `autopilot.in_air_reset.reset_in_air` re-spawns the world with every vehicle hovering at
  the start altitude, PX4's sensors measuring a continuous flight (their position offset
  takes the jump), and settles `settle_s` under the zero setpoint; observations keep reading
  the truth. Where PX4 is not in a clean flying state (disarmed, failsafe, landed, crashed,
  tumbling, estimate off, offset past its bound), or at the first episode, it falls back to:
* a restart (`px4`: a cold boot is the only reset that clears all of PX4's state): the
  session is restarted, autopilot processes, links and MAVSDK clients, on the same instances;
  after the take-off the first episode is placed in the air as an in-air reset places it, so
  where a take-off ended and how far PX4's estimate was off do not vary the episode's start.
The offboard setpoints hold each vehicle's spawn heading.

Collisions come from the session's collision log (`SimSession.take_collisions`), each
physics step's exactly once; a new setpoint reaches in-process stubs before the first step
of its span (`SimSession.deliver_pending_commands`), as in `direct`.
"""

from __future__ import annotations

import contextlib
import logging
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from sitl_bridge.autopilot.allocation import InstanceClaim, claim_free_instances
from sitl_bridge.autopilot.in_air_reset import reset_in_air
from sitl_bridge.autopilot.registry import env_kind
from sitl_bridge.client import Fleet, OffboardClientError
from sitl_bridge.envs.backends.base import EPISODE_START, BackendError, CollisionFlags, Snapshot
from sitl_bridge.envs.options import EnvOptions
from sitl_bridge.frames import yaw_enu_to_ned
from sitl_bridge.hil import HilError
from sitl_bridge.sensors import sensor_seed
from sitl_bridge.sensors.lidar import Lidar
from sitl_bridge.session import SessionError, SimSession
from sitl_bridge.world import World
from sitl_bridge.world.clock import nearest_whole_steps_s

log = logging.getLogger(__name__)

FIRST_PLACEMENT_TRIES = 2
"""Starts (boot, take-off, placement in the air) of a kind that resets in the air before the
first episode's placement counts as failed."""


class SessionBackend:
    """A `SimSession` with a MAVSDK `Fleet`, flown through the Backend API."""

    def __init__(self, world: World, options: EnvOptions, *, start_altitude_m: float, takeoff: bool = False) -> None:
        self.estimator = options.estimator
        self.name = options.autopilot
        fleet_class = env_kind(options.autopilot).fleet_class()
        self.resets_in_place = fleet_class.resets_in_place
        self.takeoff = takeoff
        """Every episode flies its take-off (a kind that resets in the air restarts for it)."""
        self.resets_in_air = fleet_class.resets_in_air and not takeoff
        self.places_in_air = fleet_class.places_in_air and not takeoff
        """Episodes start placed in the air, no take-off flown (`AutopilotFleet.place_in_air`)."""
        self.in_air_resets = 0
        """Episodes started in the air (`reset_in_air`); the others were restarts or in place."""
        self.last_in_air_refusal = ""
        """Why the last reset could not start in the air ('' when it did)."""
        self.world = world
        self.num_drones = world.num_vehicles
        self.start_altitude_m = float(start_altitude_m)
        self._session_options: dict[str, Any] = dict(
            autopilot=options.autopilot, speed_factor=options.speed_factor,
            instance_base=options.instance_base, px4_bin=options.px4_bin, gui=options.uses_gui,
            visual=options.render_mode is not None,
            ground_truth_estimate=options.ground_truth,
            # MAVSDK here reads only mode, armed, landed state, position and health: the API
            # link's full onboard telemetry would cost MAVSDK and PX4 CPU every step (px4)
            api_telemetry="client")
        self.session: SimSession | None = None
        self.fleet: Fleet | None = None
        self.claim: InstanceClaim | None = None
        """The vehicle instances this env runs on, held from its first start to `close()`."""
        self.lidar: Lidar | None = None
        self._collisions = CollisionFlags(self.num_drones)
        self._episode_start_us = 0
        self._closed = False

    # -- Backend API --------------------------------------------------------------------
    def reset(self, seed: int | None = None) -> Snapshot:
        seed = 0 if seed is None else int(seed)
        snapshot = self.fly_on(seed)
        if snapshot is not None:
            return snapshot
        for attempt in range(FIRST_PLACEMENT_TRIES):
            if self.session is not None and not self.resets_in_place:
                self._stop()  # e.g. PX4: restart rather than teleport its estimator
            if self.session is None:
                self._start(seed)
            session = self._session()
            if self.resets_in_place:
                # Also right after a start: connecting let time run, and every episode must begin
                # from the same state as `direct`'s (rebooted autopilot, freshly seeded sensors).
                session.reset(seed)
                assert self.lidar is not None
                self.lidar.reset()
            # Otherwise the autopilots just started on the episode's layout (drawn from `seed`).
            self._episode_start_us = session.time_us
            if self.places_in_air:
                with session.exclusive():
                    session.autopilots.place_in_air(session.lockstep, self.start_altitude_m)
                self._offboard_and_settle()
            else:
                self._hover_start()
            if not self.resets_in_air:
                break
            # The first episode after a boot starts placed as every in-air episode does (where
            # the take-off ended, and the truth against PX4's estimate, vary from boot to boot).
            refusal = self._place_in_air(seed)
            if not refusal:
                self._episode_begins()
                return self._snapshot()
            log.warning("%s: the first episode could not be placed in the air (%s)%s", self.name, refusal,
                        "; starting again" if attempt + 1 < FIRST_PLACEMENT_TRIES else "")
        else:
            raise BackendError(f"{self.name}: the first episode after a start could not be placed "
                               f"in the air: {refusal}")
        session.take_collisions()  # the episode start's do not count
        self._collisions.clear()
        return self._snapshot()

    def fly(self, velocities_ned_m_s: Sequence[np.ndarray], duration_s: float,
            yaws_ned_rad: Sequence[float] | None = None) -> Snapshot:
        fleet = self._fleet()
        session = self._session()
        if len(velocities_ned_m_s) != self.num_drones:
            raise ValueError(f"expected {self.num_drones} velocities, got {len(velocities_ned_m_s)}")
        session.take_collisions()  # none since the last call's end, which was held
        try:
            # the fleet makes every setpoint reach its stub before time resumes, as in `direct`
            fleet.fly([np.asarray(v, dtype=float) for v in velocities_ned_m_s], duration_s,
                      None if yaws_ned_rad is None else [math.degrees(float(y)) for y in yaws_ned_rad])
        except SessionError as exc:
            raise BackendError(f"{self.name}: {exc}") from None
        self._collisions.clear()
        for collision in session.take_collisions():
            self._collisions.add(collision)
        return self._snapshot()

    def fly_on(self, seed: int) -> Snapshot | None:
        """The next episode in the air, the autopilots flying on (module docstring), where they
        can; None where they cannot (not started, a kind that does not, or refused:
        `last_in_air_refusal` says why; the simulation may then have been reset already)."""
        if self.session is None or not self.resets_in_air or not self._reset_in_air(seed):
            return None
        return self._snapshot()

    def restart(self, seed: int) -> Snapshot:
        """The next episode on freshly started autopilots (a cold boot for every kind)."""
        self._stop()
        return self.reset(seed)

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._stop()
            self._release()

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
        if self.claim is None:
            # The pick is the claim, held until close(): no run starting at the same moment can
            # take these instances, and restarts (px4) come back on them. `instance_base` is a
            # preference: taken when free, else the next free block the kind can run on.
            fleet_class = env_kind(self.name).fleet_class()
            self.claim = claim_free_instances(self.num_drones, self._session_options["instance_base"],
                                              fleet_class.last_instance)
        self.session = SimSession(self.world, seed=seed, **{**self._session_options, "instance_base": self.claim})
        try:
            self.session.start()
            self.fleet = Fleet(self.session.instances, clock=self.session).connect()
        except BaseException:
            self._stop()
            self._release()  # not running: the next reset picks again
            raise
        assert self.session.sim is not None
        self.lidar = Lidar(self.session.sim, [v.lidar for v in self.world.vehicles])

    def _stop(self) -> None:
        if self.fleet is not None:
            with contextlib.suppress(Exception):
                self.fleet.close()
            self.fleet = None
        if self.session is not None:
            self.session.close()
            self.session = None
        self.lidar = None

    def _release(self) -> None:
        if self.claim is not None:
            self.claim.release()
            self.claim = None

    # -- episode start --------------------------------------------------------------------------
    def _hover_start(self) -> None:
        session, fleet, start = self._session(), self._fleet(), EPISODE_START
        step_us = session.step_us
        poll_s = nearest_whole_steps_s(start.arm_poll_s, step_us)
        waited = 0.0
        while True:
            try:
                fleet.arm()
                break
            except OffboardClientError:
                if waited >= start.timeout_s:
                    raise BackendError(f"{self.name}: vehicles never became armable") from None
                session.run_for(poll_s)
                waited += poll_s
        fleet.takeoff(self.start_altitude_m, timeout_s=start.timeout_s,
                      tolerance_m=start.takeoff_tolerance_m)
        self._offboard_and_settle()

    def _offboard_and_settle(self) -> None:
        """Hovering in HOLD (after the take-off, or placed there): offboard at zero velocity, settle."""
        session, fleet = self._session(), self._fleet()
        # each holds its spawn heading: telemetry's heading is read in wall time, and which
        # report that is varies with the machine's load
        fleet.start_offboard(yaws_deg=self._spawn_headings_deg())
        session.run_for(nearest_whole_steps_s(EPISODE_START.settle_s, session.step_us))

    def _spawn_headings_deg(self) -> list[float]:
        """Every vehicle's spawn yaw as a heading (NED, degrees from north)."""
        sim = self._session().sim
        assert sim is not None
        return [math.degrees(yaw_enu_to_ned(yaw)) for yaw in sim.layout.spawn_yaws_rad]

    def _reset_in_air(self, seed: int) -> bool:
        """The next episode in the air (module docstring); False: reset another way."""
        refusal = self._place_in_air(seed)
        self.last_in_air_refusal = refusal
        if refusal:
            return False
        self.in_air_resets += 1
        self._episode_begins()
        return True

    def _place_in_air(self, seed: int) -> str:
        """Stop, then re-spawn the world for episode `seed` with every vehicle in the air where
        its autopilot estimates it (`reset_in_air`). Returns '' when done, else why not."""
        session, start = self._session(), EPISODE_START
        try:
            moving = self._stop_in_air()
            if moving:
                return f"still moving or turning after the stop: {moving}"
            seeds = [sensor_seed(seed, k) for k in range(self.num_drones)]  # as SimSession.reset
            with session.exclusive():
                return reset_in_air(session.autopilots, session.lockstep, seed, seeds, self.start_altitude_m,
                                    nearest_whole_steps_s(start.settle_s, session.step_us))
        except (SessionError, OffboardClientError, HilError) as exc:  # a dead autopilot: restart it
            return f"{type(exc).__name__}: {exc}"

    def _episode_begins(self) -> None:
        """After an in-air placement: the episode's clock, lidar and collisions start afresh."""
        assert self.lidar is not None
        self.lidar.reset()
        self._episode_start_us = 0  # simulated time restarted at 0 with the re-spawn
        self._session().take_collisions()  # the episode start's do not count
        self._collisions.clear()

    def _stop_in_air(self) -> str:
        """Zero velocity setpoints, held until every vehicle's autopilot estimates it slower
        than `in_air_stop_speed_m_s` and it turns slower than `in_air_stop_rate_rad_s` (at most
        `in_air_stop_timeout_s` of simulated time). Returns '' when they are, else which
        vehicles still move.

        The speed is the estimate's because the reset places each vehicle in the velocity its
        autopilot estimates (`autopilot.in_air_reset`), and because the controller holds that
        estimate, not the truth, at zero: after a manoeuvre PX4's estimate is off by up to
        ~0.1 m/s for seconds, so a true speed can stay above the bound the whole timeout."""
        session, fleet, start = self._session(), self._fleet(), EPISODE_START
        chunk_s = nearest_whole_steps_s(start.in_air_stop_check_s, session.step_us)
        fleet.fly([np.zeros(3)] * self.num_drones, chunk_s)
        waited = chunk_s
        while True:
            moving = self._still_moving()
            if not moving or waited >= start.in_air_stop_timeout_s:
                return moving
            session.run_for(chunk_s)  # the zero setpoint is still streaming
            waited += chunk_s

    def _still_moving(self) -> str:
        """Which vehicles are estimated faster or turn faster than the in-air stop allows."""
        session, start = self._session(), EPISODE_START
        with session.exclusive():
            estimates = session.autopilots.estimates(session.lockstep)
        moving = []
        for k, estimate in enumerate(estimates):
            state = session.vehicle_state(k)
            speed = float(np.linalg.norm(estimate.velocity_ned_m_s))
            rate = float(np.linalg.norm(state.angular_velocity_flu_rad_s))
            if speed > start.in_air_stop_speed_m_s or rate > start.in_air_stop_rate_rad_s:
                true_speed = float(np.linalg.norm(state.velocity_enu_m_s))
                moving.append(f"vehicle {k} estimated at {speed:.2f} m/s (truth {true_speed:.2f}), "
                              f"turning at {rate:.2f} rad/s")
        return "; ".join(moving)

    def with_simulation(self, use):  # noqa: ANN001, ANN201 - see Backend.with_simulation
        """`use(simulation)` with the session's runner thread off the lockstep."""
        session = self._session()
        with session.exclusive():
            return use(session.sim)

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
            collided=tuple(self._collisions.any),
            hit_obstacle=tuple(self._collisions.obstacle),
            goals=tuple(layout.goal_of(i) for i in range(self.num_drones)),  # type: ignore[arg-type]
            obstacles=layout.obstacles,
            start_delays_s=layout.start_delays_s,
            encounter=layout.encounter,
        )
