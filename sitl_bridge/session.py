"""`SimSession`: one simulation with its autopilots, ready for MAVLink clients.

Composes world -> `Simulation` -> one `SensorSuite` and `HilLink` per vehicle -> one autopilot
per vehicle -> `Lockstep` -> `SimRunner` (the background thread that owns the lockstep loop).
Autopilots:

- `stub` (default): the built-in PX4-compatible stub, in-process: its HIL client and MAVLink
  API are pumped by the lockstep in the runner thread (no context switch, the fastest path).
  With `stub_process=True` each stub is a `sitl-bridge stub -i N` subprocess instead.
- `px4`: real PX4 SITL processes (`sitl_bridge.autopilot.px4`), started, connected and
  observed ready before the session is handed over.
- `external`: only the simulator; it waits for autopilots that connect on TCP 4560+i the way
  Gazebo waits for a PX4 started by hand (`sitl-bridge stub -i N`, a PX4 of your own).

Time: the session is the clock of the MAVSDK client (`run_for(seconds)` advances exactly that
much simulated time, then holds). While held, in-process stubs keep answering MAVLink; a real
PX4 is frozen in lockstep. After `start()` the simulation is held.

Episodes: `reset(seed)` starts over in place (simulated time back to 0, vehicles re-spawned,
sensor noise re-seeded, autopilots rebooted; see its docstring for what each autopilot kind
does), keeping the ports, so MAVSDK clients stay connected. The autopilots' clock (the
`time_usec` on the HIL link) keeps counting up across it. `take_collisions()` returns what
the physics reported since the last call, `deliver_pending_commands()` waits (held) until
MAVLink commands already sent have reached the in-process stubs.

Failsafe timeouts vs. speed factor: MAVSDK streams offboard setpoints and heartbeats in wall
time (20 Hz, 1 Hz) while autopilots measure their loss timeouts in simulated time, so at F x
real time the gap between two setpoints is F times longer in simulated time. Like PX4's rcS
with PX4_SIM_SPEED_FACTOR, the timeouts marked `wall` in `px4_params/*.params`
(COM_OF_LOSS_T, COM_DL_LOSS_T, COM_RC_LOSS_T) are multiplied by the speed factor (by 30 for
F = 0, which covers up to ~600x at MAVSDK's 20 Hz), capped at the file's maximum. The session
hands F to both autopilots, which apply it through their own parameter tables: PX4 via
`autopilot.px4` (PX4_PARAM_ environment, then read back and corrected over MAVLink, since
rcS rescales some of them itself) and the stub via `ParamTable(speed_factor=F)` (in-process,
or `sitl-bridge stub --speed-factor F`). Both read the same file, so they run with the same
configuration; `params=` overrides come last (unscaled).
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import deque
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from sitl_bridge.data_paths import worlds_dirs
from sitl_bridge.errors import ConfigError
from sitl_bridge.hil import HilError, HilLink, Lockstep, SimRunner
from sitl_bridge.physics.simulation import Collision, Simulation, VehicleState
from sitl_bridge.sensors.suite import SensorSuite
from sitl_bridge.world.loader import load_world
from sitl_bridge.world.schema import Spawn, World

log = logging.getLogger(__name__)

AUTOPILOTS = ("stub", "px4", "external")
HIL_BASE_PORT = 4560
API_CLIENT_BASE_PORT = 14540
PX4_LAST_OWN_API_PORT_INSTANCE = 9
"""PX4's px4-rc.mavlink sends the API link of every instance above 9 to 14549."""
DEFAULT_WORLD = "empty"
EXTRA_VEHICLE_SPACING_M = 3.0
"""`num_vehicles` beyond the world's: copies of its last vehicle, this far apart (east)."""
COLLISION_LOG_LENGTH = 4096
"""`take_collisions()` keeps at most this many (the oldest are dropped when nobody takes them)."""
DELIVERY_TIMEOUT_S = 2.0
"""Wall seconds `deliver_pending_commands` waits by default."""
PX4_SETPOINT_DELIVERY_S = 0.02
"""Wall seconds a held session waits for PX4 to take in new setpoints (see `deliver_setpoints`)."""


class SessionError(RuntimeError):
    """The session could not start, or one of its parts died while running."""


def sensor_seed(seed: int, vehicle: int) -> int:
    """Seed of vehicle `vehicle`'s sensor noise in a session (or episode) seeded `seed`."""
    return int(seed) * 1000 + vehicle


# -- world files -----------------------------------------------------------------------------
def resolve_world(name_or_path: str | os.PathLike[str]) -> Path:
    """A world file from a path, or a bare name (`empty`, `window.yaml`) in `worlds_dirs()`."""
    path = Path(name_or_path)
    if path.is_file():
        return path
    candidates = [path.name, f"{path.name}.yaml"] if path.suffix == "" else [path.name]
    if path.parent == Path("."):
        for directory in worlds_dirs():
            for candidate in candidates:
                if (directory / candidate).is_file():
                    return directory / candidate
    searched = ", ".join(str(d) for d in worlds_dirs()) or "no worlds/ directory found"
    raise ConfigError(f"{name_or_path}: cannot find world file (searched {searched})")


def default_world_path() -> Path:
    """worlds/empty.yaml of this installation (works from any working directory)."""
    return resolve_world(DEFAULT_WORLD)


def with_vehicle_count(world: World, count: int) -> World:
    """The world with exactly `count` vehicles: extra ones copy the last vehicle's spawn,
    shifted east by `EXTRA_VEHICLE_SPACING_M` each; surplus ones are dropped."""
    if count < 1:
        raise ConfigError(f"{world.source}: vehicles: expected at least 1, got {count}")
    vehicles = list(world.vehicles[:count])
    if not vehicles:
        raise ConfigError(f"{world.source}: world.vehicles: expected at least 1 vehicle to copy, got none")
    template = vehicles[-1]
    for k in range(1, count - len(vehicles) + 1):
        x, y, z = template.spawn.position_m
        spawn: Spawn = replace(template.spawn, position_m=(x + k * EXTRA_VEHICLE_SPACING_M, y, z))
        vehicles.append(replace(template, name=f"{template.name}_{k}", spawn=spawn))
    return replace(world, vehicles=tuple(vehicles))


_MAIN_MODES = {1: "Manual", 2: "Altitude", 3: "Position", 4: "Auto", 5: "Acro", 6: "Offboard",
               7: "Stabilized", 8: "Rattitude"}
_AUTO_SUB_MODES = {1: "Ready", 2: "Takeoff", 3: "Hold", 4: "Mission", 5: "Return", 6: "Land",
                   7: "ReturnToGroundStation", 8: "FollowTarget", 9: "Precland"}


def px4_mode_name(custom_mode: int) -> str:
    """PX4 flight mode name of a HEARTBEAT custom_mode, as QGroundControl shows it."""
    main, sub = (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF
    if main == 4:
        return _AUTO_SUB_MODES.get(sub, f"Auto({sub})")
    return _MAIN_MODES.get(main, f"mode {custom_mode}")


class SimSession:
    """World + simulation + sensors + HIL links + autopilots + runner thread (see module doc).

    Args:
        world: a loaded `World`, a world file, or a bare world name (`empty`).
        autopilot: `stub`, `px4` or `external`.
        speed_factor: F x real time while running; 0 = as fast as possible.
        instance_base: vehicle k uses instance `instance_base + k` (ports 4560+i, 14580+i...).
        seed: seeds the simulation (layout, movers) and the sensor noise.
        px4_bin / px4_rootfs: PX4 SITL binary and ROMFS (`px4` only; PX4_BIN by default).
        gui: pybullet GUI.
        num_vehicles: override the world's vehicle count (see `with_vehicle_count`).
        stub_process: run stubs as `sitl-bridge stub -i N` subprocesses (`stub` only).
        stub_ground_truth: stubs use ground truth instead of estimating from the sensors.
        params: extra autopilot parameters (PX4 names), applied after px4_params/.
        run_dir: where PX4 keeps its working directories and logs (default: a temp dir).
        connect_timeout_s: wall time allowed for autopilots to connect (external: forever
            when None).
        actuator_timeout_s: wall time a lockstep step waits for an autopilot's answer.
        host: address the HIL links listen on.
    """

    def __init__(
        self,
        world: World | str | os.PathLike[str] = DEFAULT_WORLD,
        *,
        autopilot: str = "stub",
        speed_factor: float = 1.0,
        instance_base: int = 0,
        seed: int = 0,
        px4_bin: str | os.PathLike[str] | None = None,
        px4_rootfs: str | os.PathLike[str] | None = None,
        gui: bool = False,
        num_vehicles: int | None = None,
        stub_process: bool = False,
        stub_ground_truth: bool = False,
        params: Mapping[str, float] | None = None,
        run_dir: str | os.PathLike[str] | None = None,
        connect_timeout_s: float | None = 60.0,
        actuator_timeout_s: float = 5.0,
        host: str = "127.0.0.1",
    ) -> None:
        if autopilot not in AUTOPILOTS:
            raise ConfigError(f"autopilot: expected one of {', '.join(AUTOPILOTS)}, got {autopilot!r}")
        if not speed_factor >= 0:
            raise ConfigError(f"speed_factor: expected a number >= 0, got {speed_factor!r}")
        if isinstance(world, World):
            self.world = world
        else:
            self.world = load_world(resolve_world(world))
        if num_vehicles is not None:
            self.world = with_vehicle_count(self.world, num_vehicles)
        if self.world.num_vehicles < 1:
            raise ConfigError(f"{self.world.source}: world.vehicles: expected at least 1 vehicle, got none")
        self.autopilot = autopilot
        self.speed_factor = float(speed_factor)
        self.instance_base = instance_base
        self.instances = [instance_base + k for k in range(self.world.num_vehicles)]
        if autopilot == "px4" and sum(i > PX4_LAST_OWN_API_PORT_INSTANCE for i in self.instances) > 1:
            raise ConfigError(
                f"instance_base: PX4 instances above {PX4_LAST_OWN_API_PORT_INSTANCE} all send their "
                f"MAVLink API to UDP 14549; with several vehicles use instances 0..9, got "
                f"{self.instances[0]}..{self.instances[-1]}")
        self.seed = seed
        self.gui = gui
        self.host = host
        self.stub_process = stub_process
        self.stub_ground_truth = stub_ground_truth
        self.connect_timeout_s = connect_timeout_s
        self.actuator_timeout_s = actuator_timeout_s
        self.params = {name: float(value) for name, value in (params or {}).items()}
        self._px4_bin, self._px4_rootfs = px4_bin, px4_rootfs
        self._run_dir = Path(run_dir) if run_dir is not None else None
        self.sim: Simulation | None = None
        self.sensors: list[SensorSuite] = []
        self.links: list[HilLink] = []
        self.stubs: list[Any] = []         # in-process StubAutopilot per vehicle (stub only)
        self.vehicles: list[Any] = []      # their StubVehicle (autopilot + HIL client + API)
        self.lockstep: Lockstep | None = None
        self.runner: SimRunner | None = None
        self.px4: Any = None               # Px4Fleet (px4 only)
        self._processes: list[subprocess.Popen[bytes]] = []
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
        self.sim = Simulation(world, seed=self.seed, step_us=None, gui=self.gui)
        self._closers.append(self.sim.close)
        step_us = self.sim.step_us
        self.sensors = [SensorSuite(world.home, seed=sensor_seed(self.seed, k), step_us=step_us)
                        for k in range(self.num_vehicles)]
        for instance in self.instances:
            link = HilLink(instance, self.host, HIL_BASE_PORT, step_us=step_us)
            self._closers.append(link.close)
            self.links.append(link)
        pumps: list[Callable[[], Any]] = []
        if self.autopilot == "stub" and not self.stub_process:
            pumps = self._start_stubs_in_process()
        elif self.autopilot == "stub":
            self._closers.append(self._stop_processes)
            self._start_stub_processes()
        elif self.autopilot == "px4":
            self._start_px4()
        self.lockstep = Lockstep(self.sim, self.sensors, self.links, speed_factor=self.speed_factor,
                                 pumps=pumps, actuator_timeout_s=self.actuator_timeout_s)
        self.lockstep.after_step.append(self._log_collisions)
        self._accept_all()
        if self.px4 is not None:
            self.px4.wait_ready(self.lockstep)
        self.runner = SimRunner(self.lockstep)
        # First to close: the runner thread must stop before the links and sim it drives.
        self._closers.append(self.runner.close)

    def _start_stubs_in_process(self) -> list[Callable[[], Any]]:
        from sitl_bridge.autopilot.stub import ParamTable, StubVehicle

        pumps: list[Callable[[], Any]] = []
        for instance in self.instances:
            table = ParamTable(speed_factor=self.speed_factor)  # scales the `wall` timeouts
            _apply_params(table, self.params)
            vehicle = StubVehicle(instance, self.host, ground_truth_estimate=self.stub_ground_truth,
                                  params=table)
            self._closers.append(vehicle.close)
            if not vehicle.connect(self.connect_timeout_s or 10.0):
                raise SessionError(f"vehicle {instance}: stub could not connect to the HIL link")
            self.vehicles.append(vehicle)
            self.stubs.append(vehicle.autopilot)
            pumps.append(vehicle.pump)
        return pumps

    def _start_stub_processes(self) -> None:
        for instance in self.instances:
            # --once: a stub whose simulator vanished (we were killed) exits instead of waiting.
            command = [sys.executable, "-m", "sitl_bridge", "stub", "-i", str(instance), "--once",
                       "--host", self.host, "--speed-factor", repr(self.speed_factor)]
            if self.stub_ground_truth:
                command.append("--ground-truth")
            for name, value in self.params.items():
                command += ["--param", f"{name}={value!r}"]
            # Own session: a terminal's Ctrl-C reaches us only; we stop the stubs in order.
            process = subprocess.Popen(command, stdin=subprocess.DEVNULL, start_new_session=True)
            self._processes.append(process)

    def _start_px4(self) -> None:
        from sitl_bridge.autopilot.px4 import Px4Config, Px4Fleet

        run_dir = self._run_dir
        if run_dir is None:
            # Ours, so removed on close; pass run_dir to keep PX4's console logs.
            run_dir = Path(tempfile.mkdtemp(prefix="sitl-bridge-px4-"))
            self._closers.append(lambda: shutil.rmtree(run_dir, ignore_errors=True))
        # px4 resolves px4_params/ itself (wall timeouts via env + read-back); only extras here.
        config = Px4Config.create(self._px4_bin, run_dir, rootfs=self._px4_rootfs,
                                  speed_factor=self.speed_factor, home=self.world.home,
                                  extra_params=self.params)
        self.px4 = Px4Fleet(config, self.instances)
        self._closers.append(self.px4.stop)
        self.px4.start()

    def _accept_all(self) -> None:
        """Wait (wall time) until every autopilot has connected to its HIL link."""
        timeout = self.connect_timeout_s
        deadline = None if timeout is None else time.monotonic() + timeout
        pumps = self.lockstep.pumps if self.lockstep is not None else []
        for link in self.links:
            while not link.accept(0.05):
                for pump in pumps:  # in-process stubs connect from their pump
                    pump()
                self.check()
                if deadline is not None and time.monotonic() > deadline:
                    raise SessionError(
                        f"vehicle {link.instance}: no autopilot connected to TCP {link.host}:{link.port} "
                        f"within {timeout:g} s")
            if self.autopilot == "external":
                log.info("vehicle %d: autopilot connected from %s", link.instance, link.peer)

    def check(self) -> None:
        """Raise if an autopilot process died or the runner thread stopped on an error."""
        for instance, process in zip(self.instances, self._processes, strict=False):
            code = process.poll()
            if code is not None:
                raise SessionError(f"vehicle {instance}: stub process exited with code {code}")
        if self.px4 is not None:
            self.px4.check_alive()
        error = self.runner.error if self.runner is not None else None
        if error is not None:
            raise SessionError(f"the simulation stopped: {error}") from error

    def _stop_processes(self) -> None:
        for process in self._processes:
            if process.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(process.pid, signal.SIGTERM)
        for process in self._processes:
            try:
                process.wait(5.0)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(process.pid, signal.SIGKILL)
                process.wait(5.0)
        self._processes = []

    def close(self) -> None:
        """Stop the runner, the autopilots, the links and the simulation. Idempotent; safe to
        call after a partial start or from an exception handler."""
        if self._closed:
            return
        self._closed = True
        errors = []
        for closer in reversed(self._closers):
            try:
                closer()
            except Exception as exc:  # keep closing the rest
                errors.append(exc)
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
    def step_s(self) -> float:
        return self.sim.step_us * 1e-6 if self.sim is not None else 0.004

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
        block: the safe way to touch `sim`, `sensors` or `stubs` from another thread, e.g. an
        in-place episode reset. In-process stubs do not answer MAVLink meanwhile."""
        with self._require_runner().exclusive():
            yield

    # -- episodes -------------------------------------------------------------------------------
    def reset(self, seed: int | None = None) -> None:
        """Start over in place, for the next episode; returns held. Simulated time restarts
        at 0 (restarted autopilots then run until ready, so it returns a little later).

        Physics and sensors: `lockstep.reset_simulation` (vehicles re-spawned, the layout drawn
        from `seed` like a new session's; sensor suite k re-seeded `sensor_seed(seed, k)`;
        seed None keeps the generators going). The HIL links keep every autopilot's clock
        (`time_usec`) strictly increasing across the jump. The collision log is cleared.
        Autopilots, per kind:

        * `stub` in-process: each `StubVehicle.reset()` in place, a reboot of a running
          vehicle (disarmed, fresh commander/controllers/estimator, parameters kept; the
          estimator's alignment is the short warm one, see `SensorEstimator.reset`). The HIL
          connection and API sockets stay up: MAVSDK clients stay connected. Cheap (ms).
        * `px4`: `Px4Fleet.restart` (PX4's estimator cannot follow a teleport reliably): the
          processes are stopped, the simulation reset, PX4 started again on the same
          instances, reconnected and run until ready (cold boot; seconds). MAVSDK clients see
          the same system come back; reconnect them to drop what they cached.
        * `stub` subprocesses (`stub_process=True`): restarted the same way (cold boot).
        * `external`: SessionError; the session does not own those autopilots (restart them
          and the session).

        Runs under `exclusive()`: the runner thread is off the lockstep meanwhile.
        """
        runner = self._require_runner()
        if self.autopilot == "external":
            raise SessionError("reset: the autopilots are external (not started by this session), so "
                               "they cannot be rebooted with the simulation; restart them and the session")
        if seed is not None:
            self.seed = int(seed)
        lockstep = self.lockstep
        assert lockstep is not None
        sensor_seeds = None if seed is None else [sensor_seed(seed, k) for k in range(self.num_vehicles)]

        def reset_simulation() -> None:
            lockstep.reset_simulation(seed, sensor_seeds)
            self._collision_log.clear()

        with runner.exclusive():
            if self.vehicles:
                reset_simulation()
                for vehicle in self.vehicles:
                    vehicle.reset()
            elif self.px4 is not None:
                try:
                    self.px4.restart(lockstep, reset_simulation, connect_timeout_s=self.connect_timeout_s or 30.0)
                except HilError as exc:
                    raise self.px4.explain(exc) from exc
            else:  # stub subprocesses
                self._stop_processes()
                for link in self.links:
                    link.disconnect()
                reset_simulation()
                self._start_stub_processes()
                self._accept_all()

    def take_collisions(self) -> list[Collision]:
        """Every collision the physics reported since the last call (or since `start()` /
        `reset()`), oldest first, each step's exactly once (at most COLLISION_LOG_LENGTH).
        Call it while held, e.g. before and after a `run_for`."""
        log_ = self._collision_log
        taken = list(log_)
        log_.clear()
        return taken

    def _log_collisions(self) -> None:
        # Lockstep.after_step observer, in the stepping thread
        found = self.sim.collisions() if self.sim is not None else ()
        if found:
            self._collision_log.extend(found)

    def deliver_pending_commands(self, until: Callable[[], bool],
                                 timeout_s: float = DELIVERY_TIMEOUT_S) -> None:
        """Held, without advancing simulated time: serve the in-process stubs' MAVLink APIs
        (read and handle every datagram waiting on their sockets) until `until()` holds,
        e.g. until the offboard setpoints just sent through MAVSDK have arrived
        (`StubAutopilot.offboard_setpoint`). SessionError after `timeout_s` of wall time.

        Why: MAVSDK sends from its own threads in wall time; on a busy machine a datagram can
        reach a stub several simulated steps after the clock resumed, so the same commands
        would take effect at different steps from run to run. Waiting here makes them take
        effect at the first step of the next `run_for`. Returns at once without in-process
        stubs (a real PX4 reads its socket in lockstep, as PX4 does).
        """
        runner = self._require_runner()
        if not self.vehicles:
            return
        deadline = time.monotonic() + timeout_s
        while not until():
            if time.monotonic() > deadline:
                raise SessionError(f"MAVLink commands not delivered to the stubs within {timeout_s:g} s (wall)")
            with runner.exclusive() as lockstep:
                lockstep.idle(0.001)

    def deliver_setpoints(self, velocities_ned_m_s: Mapping[int, Sequence[float]],
                          timeout_s: float = DELIVERY_TIMEOUT_S) -> None:
        """Held: make sure the velocity setpoints just sent through MAVSDK (by vehicle
        instance) have reached their autopilots, so they take effect at the first step of the
        next `run_for`, whatever the machine's load.

        In-process stubs are served until each holds its new setpoint. A real PX4 reads its
        MAVLink socket in wall time even while lockstep holds its clock, so a short wall wait
        lets the datagram land. Stub subprocesses and external autopilots cannot be observed:
        nothing to wait for.
        """
        if self.autopilot == "px4":
            time.sleep(PX4_SETPOINT_DELIVERY_S)  # a delivery wait, not a flight timing
            return
        if not self.stubs:
            return
        targets = [(self.stubs[self.instances.index(instance)], tuple(float(x) for x in velocity))
                   for instance, velocity in velocities_ned_m_s.items()]

        def delivered() -> bool:
            return all(
                all(abs(a - b) <= 1e-4 for a, b in zip(stub.offboard_setpoint.velocity_ned_m_s, velocity, strict=True))
                for stub, velocity in targets)

        self.deliver_pending_commands(delivered, timeout_s)

    @property
    def real_time_factor(self) -> float:
        """Achieved simulated/wall time of the current running segment (or the last one)."""
        return self.lockstep.real_time_factor if self.lockstep is not None else 0.0

    @property
    def overall_real_time_factor(self) -> float:
        """Simulated/wall time over all running segments so far (holds excluded)."""
        return self.lockstep.stats.real_time_factor if self.lockstep is not None else 0.0

    # -- MAVLink API ----------------------------------------------------------------------------
    def api_client_port(self, vehicle: int) -> int:
        """UDP port a MAVSDK client listens on for vehicle `vehicle` (index): 14540+i, except
        real PX4 above instance 9, which sends to 14549 (px4-rc.mavlink)."""
        instance = self.instances[vehicle]
        if self.autopilot == "px4" and instance > PX4_LAST_OWN_API_PORT_INSTANCE:
            return API_CLIENT_BASE_PORT + PX4_LAST_OWN_API_PORT_INSTANCE
        return API_CLIENT_BASE_PORT + instance

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
        """(mode name, armed) of a vehicle as its autopilot reports it: the stub's own state
        in-process, else the armed flag of its HIL heartbeat/actuators (mode unknown: '-')."""
        if self.stubs:
            stub = self.stubs[vehicle]
            return px4_mode_name(stub.custom_mode), bool(stub.armed)
        if self.px4 is not None:
            obs = self.px4.autopilots[vehicle].observation
            return px4_mode_name(obs.custom_mode), bool(obs.armed)
        link = self.links[vehicle]
        armed = link.heartbeat.armed if link.heartbeat is not None else link.command.armed
        return "-", bool(armed)

    def status_line(self) -> str:
        """One line: sim time, real-time factor, per vehicle mode, armed flag, position ENU."""
        parts = [f"t={self.time_s:8.2f} s", f"rtf {self.real_time_factor:6.1f}x"]
        for k, instance in enumerate(self.instances):
            mode, armed = self.vehicle_summary(k)
            x, y, z = self.vehicle_state(k).position_enu_m
            parts.append(f"[{instance}] {mode} {'ARMED' if armed else 'disarmed'} "
                         f"E{x:+.1f} N{y:+.1f} U{z:+.1f}")
        return " | ".join(parts)


def _apply_params(table: Any, values: Mapping[str, float]) -> None:
    """Set (or add) parameters in a stub ParamTable; integers stay INT32."""
    from sitl_bridge.autopilot.stub.params import MAV_PARAM_TYPE_INT32, MAV_PARAM_TYPE_REAL32

    for name, value in values.items():
        if name in table:
            table.set(name, value)
        else:
            kind = MAV_PARAM_TYPE_INT32 if float(value).is_integer() else MAV_PARAM_TYPE_REAL32
            table.add(name, value, kind)


__all__: Sequence[str] = (
    "AUTOPILOTS",
    "COLLISION_LOG_LENGTH",
    "SessionError",
    "SimSession",
    "default_world_path",
    "px4_mode_name",
    "resolve_world",
    "sensor_seed",
    "with_vehicle_count",
)
