"""`SimSession`: one simulation with its autopilots, ready for MAVLink clients.

Composes world -> `Simulation` -> one `SensorSuite` and `HilLink` per vehicle -> one
`AutopilotFleet` (the autopilots of every vehicle, of the kind named by `autopilot=`, from
`sitl_bridge.autopilot.registry`) -> `Lockstep` -> `SimRunner` (the background thread that owns
the lockstep loop). The session never asks which kind it runs: starting, readiness, faults,
resets, setpoint delivery, mode/armed summaries and ports are the fleet's
(`sitl_bridge.autopilot.fleet`). Shipped kinds: `stub` (in-process, default), `stub-process`,
`px4`, `external` (see the registry).

Time: the session is the clock of the MAVSDK client (`run_for(seconds)` advances exactly that
much simulated time, then holds). While held, in-process stubs keep answering MAVLink; a real
PX4 is frozen in lockstep. After `start()` the simulation is held.

Episodes: `reset(seed)` starts over in place (time back to 0, vehicles re-spawned, sensor noise
re-seeded, autopilots rebooted by their fleet's `reset`), keeping the ports: MAVSDK stays connected.
The autopilots' clock (HIL `time_usec`) keeps counting up. `take_collisions()` returns what
the physics reported since the last call.

Failsafe timeouts scale with the speed factor: see `sitl_bridge.autopilot.fleet`.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
from collections import deque
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path

from sitl_bridge.autopilot.allocation import InstanceClaim, hold_instances
from sitl_bridge.autopilot.fleet import AutopilotFault, AutopilotFleet, FleetConfig, SessionError
from sitl_bridge.autopilot.registry import session_kind
from sitl_bridge.errors import ConfigError
from sitl_bridge.hil import HilError, HilLink, Lockstep, SimRunner
from sitl_bridge.physics.simulation import Collision, Simulation, VehicleState
from sitl_bridge.ports import VehiclePorts
from sitl_bridge.sensors import SensorSuite, sensor_seed
from sitl_bridge.world import World, default_world_path, resolve_world, with_vehicle_count
from sitl_bridge.world.loader import load_world
from sitl_bridge.world.lookup import DEFAULT_WORLD

log = logging.getLogger(__name__)

COLLISION_LOG_LENGTH = 4096
"""`take_collisions()` keeps at most this many (the oldest are dropped when nobody takes them)."""
DELIVERY_TIMEOUT_S = 2.0
"""Wall seconds `deliver_pending_commands` waits by default."""


class SimSession:
    """World + simulation + sensors + HIL links + autopilots + runner thread (see module doc).

    Args:
        world: a loaded `World`, a world file, or a bare world name (`empty`).
        autopilot: a session kind of `sitl_bridge.autopilot.registry` (`stub`, `stub-process`,
            `px4`, `external`, or one registered at run time).
        speed_factor: F x real time while running; 0 = as fast as possible.
        instance_base: vehicle k uses instance `instance_base + k` (ports: `sitl_bridge.ports`),
            claimed until `close()`; or a held `InstanceClaim` to adopt (`autopilot.allocation`).
        seed: seeds the simulation (layout, movers) and the sensor noise.
        px4_bin / px4_rootfs: PX4 SITL binary and ROMFS (`px4` only; PX4_BIN by default).
        gui: pybullet GUI. visual: coloured bodies for offscreen pictures (`physics.render`).
        num_vehicles: override the world's count (`with_vehicle_count`).
        ground_truth_estimate: autopilots estimate from ground truth (kinds that support it).
        params: extra autopilot parameters (PX4 names), applied after px4_params/.
        run_dir: where autopilot processes keep working directories and logs (default: temp).
        connect_timeout_s: wall time allowed for autopilots to connect (None: forever).
        actuator_timeout_s: wall time a lockstep step waits for an autopilot's answer.
        host: address the HIL links listen on. api_telemetry: see `FleetConfig.api_telemetry`.
    """

    def __init__(
        self,
        world: World | str | os.PathLike[str] = DEFAULT_WORLD,
        *,
        autopilot: str = "stub",
        speed_factor: float = 1.0,
        instance_base: int | InstanceClaim = 0,
        seed: int = 0,
        px4_bin: str | os.PathLike[str] | None = None,
        px4_rootfs: str | os.PathLike[str] | None = None,
        gui: bool = False,
        visual: bool = False,
        num_vehicles: int | None = None,
        ground_truth_estimate: bool = False,
        params: Mapping[str, float] | None = None,
        run_dir: str | os.PathLike[str] | None = None,
        connect_timeout_s: float | None = 60.0,
        actuator_timeout_s: float = 5.0,
        host: str = "127.0.0.1", api_telemetry: str = "full",
    ) -> None:
        fleet_class = session_kind(autopilot).fleet_class()
        if not speed_factor >= 0:
            raise ConfigError(f"speed_factor: expected a number >= 0, got {speed_factor!r}")
        if ground_truth_estimate and not fleet_class.supports_ground_truth:
            raise ConfigError(f"ground_truth_estimate: the {autopilot} autopilot estimates from its sensors only")
        self.world = world if isinstance(world, World) else load_world(resolve_world(world))
        if num_vehicles is not None:
            self.world = with_vehicle_count(self.world, num_vehicles)
        if self.world.num_vehicles < 1:
            raise ConfigError(f"{self.world.source}: world.vehicles: expected at least 1 vehicle, got none")
        self.autopilot = autopilot
        self.speed_factor = float(speed_factor)
        self._claim = instance_base if isinstance(instance_base, InstanceClaim) else None  # the caller's
        self.instance_base = instance_base if self._claim is None else self._claim.base
        self.instances = [self.instance_base + k for k in range(self.world.num_vehicles)]
        self.seed = seed
        self.gui, self.visual = gui, visual
        self.host = host
        self.actuator_timeout_s = actuator_timeout_s
        self.autopilots: AutopilotFleet = fleet_class(FleetConfig(
            world=self.world, instances=tuple(self.instances), host=host, speed_factor=self.speed_factor,
            params={name: float(value) for name, value in (params or {}).items()},
            ground_truth_estimate=ground_truth_estimate, connect_timeout_s=connect_timeout_s,
            px4_bin=None if px4_bin is None else os.fspath(px4_bin),
            px4_rootfs=None if px4_rootfs is None else os.fspath(px4_rootfs),
            run_dir=None if run_dir is None else Path(run_dir), api_telemetry=api_telemetry))
        self.sim: Simulation | None = None
        self.sensors: list[SensorSuite] = []
        self.links: list[HilLink] = []
        self.lockstep: Lockstep | None = None
        self.runner: SimRunner | None = None
        self._closers: list[Callable[[], None]] = []
        self._collision_log: deque[Collision] = deque(maxlen=COLLISION_LOG_LENGTH)
        self._started = False
        self._closed = False

    # -- lifecycle --------------------------------------------------------------------------
    @property
    def num_vehicles(self) -> int:
        return self.world.num_vehicles

    def start(self) -> SimSession:
        """Build everything, connect every autopilot, and leave the simulation held."""
        if self._started:
            return self
        self._started = True
        try:
            self._start()
        except BaseException:
            self.close()
            raise
        return self

    def _start(self) -> None:
        world = self.world
        if self.gui and sys.platform.startswith("linux") and not os.environ.get("DISPLAY"):
            # pybullet would exit(1) from C without a word of ours
            raise SessionError("--gui needs a display, and DISPLAY is not set")
        self._closers.append(hold_instances(self.instances, self._claim))  # the first in: freed last
        self.sim = Simulation(world, seed=self.seed, step_us=None, gui=self.gui, visual=self.visual)
        self._closers.append(self.sim.close)
        step_us = self.sim.step_us
        self.sensors = [SensorSuite(world.home, seed=sensor_seed(self.seed, k), step_us=step_us)
                        for k in range(self.num_vehicles)]
        for instance in self.instances:
            link = HilLink(instance, self.host, step_us=step_us,
                           ground_truth=self.autopilots.reads_hil_ground_truth)
            self._closers.append(link.close)
            self.links.append(link)
        self._closers.append(self.autopilots.close)
        pumps = self.autopilots.start(self.links)
        self.lockstep = Lockstep(self.sim, self.sensors, self.links, speed_factor=self.speed_factor,
                                 pumps=pumps, actuator_timeout_s=self.actuator_timeout_s)
        self.lockstep.after_step.append(self._log_collisions)
        self.autopilots.connect(self.links, pumps)
        self.autopilots.wait_ready(self.lockstep)
        self.runner = SimRunner(self.lockstep)
        # First to close: the runner thread must stop before the links and sim it drives.
        self._closers.append(self.runner.close)

    def faults(self) -> list[AutopilotFault]:
        """Every dead or frozen autopilot now ([] when healthy): the fleet's `check()` plus a
        lockstep failure that stopped the runner thread (taken: reported once). What a
        supervisor acts on, e.g. with `restart_autopilots()`."""
        faults, runner = self.autopilots.check(), self.runner
        explained = self.autopilots.explain(runner.error) if runner and runner.error else None
        if runner is not None and isinstance(explained, AutopilotFault):
            runner.error = None
            faults += [explained] if all(f.instance != explained.instance for f in faults) else []
        return faults

    def check(self) -> None:
        """Raise the first `AutopilotFault`, or a SessionError if the runner stopped otherwise."""
        faults = self.faults()
        if faults:
            raise faults[0]
        error = self.runner.error if self.runner is not None else None
        if error is not None:
            raise SessionError(f"the simulation stopped: {error}") from error

    def restart_autopilots(self) -> None:
        """Hold (a running simulation too) and cold-restart every autopilot (simulation
        untouched), the cure for `faults()`; returns held."""
        runner = self._require_runner()
        # the held runner thread may fail on the dead link until the restart takes it over
        with runner.exclusive(discard_error=True) as lockstep:
            self.autopilots.restart(lockstep)

    def close(self) -> None:
        """Stop the runner, autopilots, links and simulation. Idempotent (partial starts too)."""
        if self._closed:
            return
        self._closed = True
        for closer in reversed(self._closers):
            try:
                closer()
            except Exception as exc:  # keep closing the rest
                log.warning("while closing the session: %s", exc)
        self._closers.clear()

    def __enter__(self) -> SimSession:
        return self.start()

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # -- clock ----------------------------------------------------------------------------------
    def _require_runner(self) -> SimRunner:
        if self.runner is None or self._closed:
            raise SessionError("session is not running (use `with SimSession(...)` or start())")
        return self.runner

    @property
    def time_us(self) -> int:
        """Simulated time in microseconds."""
        return self.sim.time_us if self.sim is not None else 0

    @property
    def time_s(self) -> float:
        return self.time_us * 1e-6

    @property
    def step_us(self) -> int:
        """The physics step (the world's `physics.step_us`)."""
        return self.sim.step_us if self.sim is not None else self.world.physics.step_us

    @property
    def step_s(self) -> float:
        return self.step_us * 1e-6

    @property
    def running(self) -> bool:
        """True while simulated time advances (free-running or inside a run_for)."""
        return self.runner is not None and self.runner.running

    def run_for(self, seconds: float, wait: bool = True) -> None:
        """Advance exactly `seconds` of simulated time (whole physics steps), then hold.
        With `wait=False` return at once; `wait_held()` then waits for the end."""
        runner = self._require_runner()
        runner.run_for(seconds, wait=False)
        if wait:
            self.wait_held()

    def wait_held(self, timeout_s: float | None = None) -> bool:
        """Block until the simulation is held; False if still running after `timeout_s` wall."""
        runner = self._require_runner()
        try:
            runner.wait(timeout_s)
        except TimeoutError:
            return False
        except HilError as exc:  # a dead or frozen autopilot: say which (AutopilotFault)
            explained = self.autopilots.explain(exc)
            raise explained from (None if explained is exc else exc)
        return True

    def resume(self) -> None:
        """Free-run at the speed factor until `hold()` or `run_for()`."""
        self._require_runner().resume()

    def hold(self) -> None:
        """Stop at the next step boundary (returns once held)."""
        self._require_runner().hold()

    @contextlib.contextmanager
    def exclusive(self) -> Iterator[None]:
        """Held, with the runner thread off the lockstep (not even idling the pumps) inside the
        block: the safe way to touch `sim`, `sensors` or in-process autopilots from another
        thread, e.g. an in-place episode reset. In-process stubs do not answer MAVLink meanwhile."""
        with self._require_runner().exclusive():
            yield

    # -- episodes -------------------------------------------------------------------------------
    def reset(self, seed: int | None = None) -> None:
        """Start over for the next episode; returns held. Simulated time restarts at 0
        (restarted autopilots then run until ready, so it returns a little later).

        Physics and sensors: `lockstep.reset_simulation` (vehicles re-spawned, the layout drawn
        from `seed` like a new session's; sensor suite k re-seeded `sensor_seed(seed, k)`;
        seed None keeps the generators going); the HIL links keep every autopilot's clock
        increasing; the collision log is cleared. Autopilots: their fleet's `reset` (stub:
        reboot in place, MAVSDK stays connected; px4, stub-process: processes restarted;
        external: SessionError, the session does not own them).
        Runs under `exclusive()`: the runner thread is off the lockstep meanwhile.
        """
        runner = self._require_runner()
        sensor_seeds = None if seed is None else [sensor_seed(seed, k) for k in range(self.num_vehicles)]
        with runner.exclusive() as lockstep:
            def reset_simulation() -> None:
                lockstep.reset_simulation(seed, sensor_seeds)
                self._collision_log.clear()

            self.autopilots.reset(lockstep, reset_simulation)
        if seed is not None:
            self.seed = int(seed)

    def take_collisions(self) -> list[Collision]:
        """Every collision the physics reported since the last call (or since `start()` /
        `reset()`), oldest first, each step's exactly once (at most COLLISION_LOG_LENGTH).
        Call it while held, e.g. before and after a `run_for`."""
        taken = list(self._collision_log)
        self._collision_log.clear()
        return taken

    def _log_collisions(self) -> None:
        # Lockstep.after_step observer, in the stepping thread; the cheap test first (collisions()
        # copies its list, every step)
        sim = self.sim
        if sim is not None and sim.has_collisions:
            self._collision_log.extend(sim.collisions())

    def deliver_pending_commands(self, until: Callable[[], bool],
                                 timeout_s: float = DELIVERY_TIMEOUT_S) -> None:
        """Held, without advancing simulated time: serve the in-process autopilots' MAVLink
        APIs (the lockstep's pumps) until `until()` holds, e.g. until the offboard setpoints
        just sent through MAVSDK have arrived; SessionError after `timeout_s` (wall). MAVSDK
        sends in wall time from its own threads: without this wait a busy machine would let
        the same command act at different steps from run to run. Returns at once without
        in-process autopilots (a real PX4 reads its socket in lockstep, as PX4 does)."""
        if not self._require_runner().serve_until(until, timeout_s):
            raise SessionError(f"MAVLink commands not delivered to the stubs within {timeout_s:g} s (wall)")

    def deliver_setpoints(self, velocities_ned_m_s: Mapping[int, Sequence[float]],
                          timeout_s: float = DELIVERY_TIMEOUT_S) -> None:
        """Held: make sure the velocity setpoints just sent through MAVSDK (by vehicle
        instance) have reached their autopilots, so they take effect at the first step of the
        next `run_for`, whatever the machine's load (how: `AutopilotFleet.deliver_setpoints`)."""
        self.autopilots.deliver_setpoints(velocities_ned_m_s, self.deliver_pending_commands, timeout_s)

    @property
    def real_time_factor(self) -> float:
        """Achieved simulated/wall time of the current running segment (or the last one)."""
        return self.lockstep.real_time_factor if self.lockstep is not None else 0.0

    @property
    def overall_real_time_factor(self) -> float:
        """Simulated/wall time over all running segments so far (holds excluded)."""
        return self.lockstep.stats.real_time_factor if self.lockstep is not None else 0.0

    # -- MAVLink API ----------------------------------------------------------------------------
    def ports(self, vehicle: int) -> VehiclePorts:
        """The ports of vehicle `vehicle` (index) as its autopilot kind serves them."""
        return self.autopilots.ports(vehicle)

    def api_client_port(self, vehicle: int) -> int:
        """UDP port a MAVSDK client listens on for vehicle `vehicle` (index)."""
        return self.ports(vehicle).api_client

    @property
    def api_urls(self) -> list[str]:
        """MAVSDK connection URL of every vehicle (`udpin://127.0.0.1:<port>`)."""
        return [f"udpin://{self.host}:{self.api_client_port(k)}" for k in range(self.num_vehicles)]

    # -- observation -------------------------------------------------------------------------
    def vehicle_state(self, vehicle: int) -> VehicleState:
        """Ground truth of vehicle `vehicle` (index, not instance). Read it while held."""
        if self.sim is None:
            raise SessionError("session is not running")
        return self.sim.state(vehicle)

    def vehicle_summary(self, vehicle: int) -> tuple[str, bool]:
        """(mode name, armed) of a vehicle as its autopilot reports it ('-': mode unknown)."""
        summary = self.autopilots.summary(vehicle, self.links[vehicle])
        return summary.mode, summary.armed

    def status_line(self) -> str:
        """One line: sim time, real-time factor, per vehicle mode, armed flag, position ENU."""
        parts = [f"t={self.time_s:8.2f} s", f"rtf {self.real_time_factor:6.1f}x"]
        for k, instance in enumerate(self.instances):
            mode, armed = self.vehicle_summary(k)
            # `or 0.0` turns a rounded -0.0 into 0.0 (no "E-0.0" for a vehicle at the origin).
            x, y, z = (round(float(v), 1) or 0.0 for v in self.vehicle_state(k).position_enu_m)
            parts.append(f"[{instance}] {mode} {'ARMED' if armed else 'disarmed'} "
                         f"E{x:+.1f} N{y:+.1f} U{z:+.1f}")
        return " | ".join(parts)


__all__: Sequence[str] = ("COLLISION_LOG_LENGTH", "SessionError", "SimSession", "default_world_path")
