"""One PX4 SITL process: locating the build, environment, working directory, console log,
start/stop without orphans, death reports. See the package docstring."""

from __future__ import annotations

import atexit
import collections
import contextlib
import fcntl
import logging
import os
import shutil
import signal
import subprocess
import threading
import weakref
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sitl_bridge.autopilot.px4.observer import GcsObserver, Px4Observation
from sitl_bridge.autopilot.px4.params import (
    PARAMS_DIR,
    Px4Param,
    format_value,
    load_param_overrides,
)
from sitl_bridge.lifetime import die_with_parent
from sitl_bridge.ports import PX4_LAST_OWN_API_INSTANCE, api_client_port

log = logging.getLogger(__name__)

DEFAULT_AIRFRAME = "gazebo-classic_iris"
DEFAULT_LOG_CAP_BYTES = 20 * 1024 * 1024
READY_LINE = "Ready for takeoff"
RC_MAVLINK = PARAMS_DIR / "px4-rc.mavlink"
"""Our MAVLink startup script (only the GCS and API links; see the file), found by rcS's
`. px4-rc.mavlink` before PX4's own because its folder comes first on PX4's PATH."""


API_STREAMS = ("onboard", "client")
"""`Px4Config.api_streams` choices (px4-rc.mavlink reads SITL_BRIDGE_API_STREAMS)."""


class Px4Error(RuntimeError):
    """PX4 could not be found, started or made ready."""


class Px4Died(Px4Error):
    """A PX4 process exited; the message carries the tail of its console output."""

    def __init__(self, message: str, *, instance: int, returncode: int | None, tail: str) -> None:
        super().__init__(message)
        self.instance = instance
        self.returncode = returncode
        self.tail = tail


# -- locating the build ------------------------------------------------------------------------
def find_px4_bin(path: str | os.PathLike[str] | None = None) -> Path:
    """The PX4 binary from `path` (`--px4-bin`) or the PX4_BIN environment variable."""
    text = os.fspath(path) if path else os.environ.get("PX4_BIN", "")
    if not text:
        raise Px4Error("no PX4 binary: pass --px4-bin PATH or set PX4_BIN (px4_sitl_default bin/px4)")
    binary = Path(text).expanduser().resolve()
    if not binary.is_file() or not os.access(binary, os.X_OK):
        raise Px4Error(f"PX4 binary {binary} does not exist or is not executable")
    return binary


def find_rootfs(px4_bin: Path, rootfs: str | os.PathLike[str] | None = None) -> Path:
    """PX4's ROMFS `etc` directory (contains init.d-posix/rcS): `rootfs` (`--px4-rootfs`,
    either the etc directory or one containing it) or `<build>/etc` next to `bin/px4`."""
    candidates = []
    if rootfs:
        given = Path(rootfs).expanduser().resolve()
        candidates += [given, given / "etc"]
    else:
        candidates += [px4_bin.parent.parent / "etc", px4_bin.parent / "etc"]
    for candidate in candidates:
        if (candidate / "init.d-posix" / "rcS").is_file():
            return candidate
    where = ", ".join(str(c) for c in candidates)
    raise Px4Error(f"PX4 ROMFS not found (no init.d-posix/rcS in {where}); pass --px4-rootfs")


def px4_server_running(instance: int) -> bool:
    """True when a PX4 server runs as instance `instance`: PX4 holds a POSIX record lock on
    /tmp/px4_lock-N while it runs (a file left by a killed PX4 is not locked)."""
    try:
        fd = os.open(f"/tmp/px4_lock-{instance}", os.O_RDWR)
    except OSError:
        return False
    try:
        fcntl.lockf(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return True
    else:
        fcntl.lockf(fd, fcntl.LOCK_UN)
        return False
    finally:
        os.close(fd)


# -- configuration --------------------------------------------------------------------------------
@dataclass(frozen=True)
class Px4Config:
    """How to run PX4 for every vehicle of a session."""

    px4_bin: Path
    run_dir: Path
    rootfs: Path | None = None
    speed_factor: float = 1.0
    home_lat_deg: float = 47.397742
    home_lon_deg: float = 8.545594
    home_alt_m: float = 488.0
    airframe: str = DEFAULT_AIRFRAME
    params: Mapping[str, Px4Param] = field(default_factory=load_param_overrides)
    sim_host: str = "127.0.0.1"
    log_cap_bytes: int = DEFAULT_LOG_CAP_BYTES
    keep_logs: bool = True
    """False: `run_dir` is a temp dir removed on close, so reports do not name console.log."""
    api_streams: str = "onboard"
    """What the MAVLink API link (MAVSDK's) streams: "onboard", PX4's onboard set (~50 streams,
    what a user's MAVSDK script may expect), or "client", only what `sitl_bridge.client` reads
    (px4-rc.mavlink lists them): MAVSDK and PX4 then spend far less CPU per simulated second."""

    def __post_init__(self) -> None:
        if self.api_streams not in API_STREAMS:
            raise Px4Error(f"api_streams: expected one of {', '.join(API_STREAMS)}, got {self.api_streams!r}")

    @classmethod
    def create(
        cls,
        px4_bin: str | os.PathLike[str] | None,
        run_dir: str | os.PathLike[str],
        *,
        rootfs: str | os.PathLike[str] | None = None,
        speed_factor: float = 1.0,
        home: Any = None,
        params_dir: str | os.PathLike[str] | None = None,
        extra_params: Mapping[str, float | int] | None = None,
        **kwargs: Any,
    ) -> Px4Config:
        """Resolve the binary (`--px4-bin`/PX4_BIN), ROMFS and overrides; `home` is a
        `GeoHome` (lat_deg, lon_deg, alt_m) or None for Gazebo's default."""
        binary = find_px4_bin(px4_bin)
        if home is not None:
            kwargs.update(home_lat_deg=home.lat_deg, home_lon_deg=home.lon_deg, home_alt_m=home.alt_m)
        return cls(
            px4_bin=binary,
            run_dir=Path(run_dir),
            rootfs=find_rootfs(binary, rootfs),
            speed_factor=speed_factor,
            params=load_param_overrides(params_dir, extra_params),
            **kwargs,
        )

    def resolved_params(self) -> dict[str, float | int]:
        """Override values as PX4 gets them at this speed factor."""
        return {name: p.resolved(self.speed_factor) for name, p in self.params.items()}


# -- console capture ---------------------------------------------------------------------------------
class _Console:
    """Reads PX4's stdout/stderr in a thread: capped log file, in-memory tail, markers."""

    def __init__(self, stream: Any, path: Path, cap_bytes: int) -> None:
        self.path = path
        self.cap_bytes = cap_bytes
        self.tail_lines: collections.deque[str] = collections.deque(maxlen=200)
        self.ready_for_takeoff = False
        self._stream = stream
        self._thread = threading.Thread(target=self._run, name=f"px4-console-{path.parent.name}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        written = 0
        out = self.path.open("ab")
        try:
            for raw in iter(self._stream.readline, b""):
                line = raw.decode("utf-8", "replace").rstrip()
                self.tail_lines.append(line)
                if READY_LINE in line:
                    self.ready_for_takeoff = True
                if written + len(raw) > self.cap_bytes // 2:
                    # Rotate: keep the current and the previous half, never more than the cap.
                    out.close()
                    os.replace(self.path, self.path.with_suffix(".log.1"))
                    out = self.path.open("wb")
                    written = 0
                out.write(raw)
                out.flush()
                written += len(raw)
        except (OSError, ValueError):
            pass
        finally:
            out.close()
            with contextlib.suppress(OSError):
                self._stream.close()

    def join(self, timeout_s: float) -> None:
        self._thread.join(timeout_s)

    def tail(self, lines: int = 40) -> str:
        return "\n".join(list(self.tail_lines)[-lines:])


# -- one PX4 process -------------------------------------------------------------------------------
_LIVE: weakref.WeakSet[Px4Autopilot] = weakref.WeakSet()


def _stop_all_at_exit() -> None:
    for autopilot in list(_LIVE):
        with contextlib.suppress(Exception):
            autopilot.stop(timeout_s=2.0)


atexit.register(_stop_all_at_exit)


class Px4Autopilot:
    """One PX4 SITL process for vehicle `instance` (see module docstring).

    Start it from a thread that lives as long as PX4 should (normally the main thread): the
    parent-death signal fires when the starting thread ends.
    """

    def __init__(self, config: Px4Config, instance: int) -> None:
        if not 0 <= instance <= 254:
            raise Px4Error(f"PX4 instance must be in 0..254 (MAV_SYS_ID = instance + 1), got {instance}")
        if instance > PX4_LAST_OWN_API_INSTANCE:
            log.warning("PX4 instance %d: PX4's px4-rc.mavlink sends the API link of every instance "
                        "above %d to UDP %d, not %d", instance, PX4_LAST_OWN_API_INSTANCE,
                        api_client_port(instance, px4=True), api_client_port(instance))
        self.config = config
        self.instance = instance
        self.work_dir = config.run_dir / "px4" / str(instance)
        self.console_log = self.work_dir / "console.log"
        self.observation = Px4Observation()
        self.starts = 0
        self._process: subprocess.Popen[bytes] | None = None
        self._console: _Console | None = None
        self._observer: GcsObserver | None = None

    # -- lifecycle ------------------------------------------------------------------------
    def environment(self) -> dict[str, str]:
        """The environment PX4 is started with."""
        config = self.config
        env = dict(os.environ)
        for key in list(env):
            if key.startswith("PX4_PARAM_") or key in ("PX4_SYS_AUTOSTART", "PX4_SIM_SPEED_FACTOR",
                                                         "SITL_BRIDGE_API_STREAMS"):
                del env[key]  # only what this configuration says
        env["SITL_BRIDGE_API_STREAMS"] = config.api_streams
        env["PX4_SIM_MODEL"] = config.airframe
        if config.speed_factor > 0:
            env["PX4_SIM_SPEED_FACTOR"] = format_value(config.speed_factor)
        env["PX4_HOME_LAT"] = f"{config.home_lat_deg:.9f}"
        env["PX4_HOME_LON"] = f"{config.home_lon_deg:.9f}"
        env["PX4_HOME_ALT"] = f"{config.home_alt_m:.3f}"
        if (self.work_dir / "rc" / RC_MAVLINK.name).is_file():
            env["PATH"] = f"{self.work_dir / 'rc'}{os.pathsep}{env.get('PATH', os.defpath)}"
        if config.sim_host not in ("127.0.0.1", "localhost"):
            env["PX4_SIM_HOST_ADDR"] = config.sim_host
        for name, value in config.resolved_params().items():
            env[f"PX4_PARAM_{name}"] = format_value(value)
        return env

    def _prepare_work_dir(self) -> None:
        self.work_dir.mkdir(parents=True, exist_ok=True)
        # Parameters PX4 saved last time would override the airframe and our overrides.
        for stale in ("parameters.bson", "parameters_backup.bson", "dataman"):
            with contextlib.suppress(FileNotFoundError):
                (self.work_dir / stale).unlink()
        shutil.rmtree(self.work_dir / "eeprom", ignore_errors=True)
        if RC_MAVLINK.is_file():
            (self.work_dir / "rc").mkdir(exist_ok=True)
            shutil.copyfile(RC_MAVLINK, self.work_dir / "rc" / RC_MAVLINK.name)
        else:
            log.warning("%s missing: PX4 starts its own MAVLink links (camera, gimbal too)", RC_MAVLINK)
        prune_logs(self.config.run_dir, self.config.log_cap_bytes)

    def start(self) -> None:
        """Start PX4 (returns at once: PX4 then connects to the simulator link and boots
        once sensor messages flow)."""
        if self.alive:
            raise Px4Error(f"PX4 instance {self.instance} is already running")
        if px4_server_running(self.instance):
            raise Px4Error(f"another PX4 already runs as instance {self.instance} (/tmp/px4_lock-{self.instance})")
        self._prepare_work_dir()
        wall = {n: p.resolved(self.config.speed_factor) for n, p in self.config.params.items() if p.wall}
        self.observation = Px4Observation(params_pending=tuple(wall))
        command = [str(self.config.px4_bin), "-i", str(self.instance), "-d", str(self.config.rootfs)]
        log.info("starting PX4 instance %d in %s", self.instance, self.work_dir)
        with self.console_log.open("ab") as out:
            out.write(f"\n==== sitl-bridge: start {self.starts + 1}: {' '.join(command)}\n".encode())
        self._process = subprocess.Popen(
            command,
            cwd=self.work_dir,
            env=self.environment(),
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            start_new_session=True,  # own process group: killed as a whole, not by our Ctrl-C
            preexec_fn=die_with_parent,  # the kernel SIGKILLs PX4 if we die without cleaning up
        )
        self.starts += 1
        _LIVE.add(self)
        self._console = _Console(self._process.stdout, self.console_log, self.config.log_cap_bytes)
        self._observer = GcsObserver(self.instance, "127.0.0.1", wall)

    def stop(self, timeout_s: float = 3.0) -> None:
        """Stop PX4 and everything it started: SIGTERM to its process group, SIGKILL after
        `timeout_s` (PX4 ignores SIGTERM until its simulator connected). Idempotent."""
        process = self._process
        if process is not None:
            if process.poll() is None:
                self._signal_group(process, signal.SIGTERM)
                try:
                    process.wait(timeout_s)
                except subprocess.TimeoutExpired:
                    log.debug("PX4 instance %d ignored SIGTERM; killing", self.instance)
            # Whatever is left in the group (rcS shell, px4-* clients) goes too.
            self._signal_group(process, signal.SIGKILL)
            with contextlib.suppress(subprocess.TimeoutExpired):
                process.wait(timeout_s)
        if self._console is not None:
            self._console.join(2.0)
        if self._observer is not None:
            self._observer.close()
        self._observer = None
        self._process = None
        _LIVE.discard(self)

    @staticmethod
    def _signal_group(process: subprocess.Popen[bytes], sig: int) -> None:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(process.pid, sig)

    def restart(self) -> None:
        """Stop and start again (fresh parameters, fresh estimator)."""
        self.stop()
        self.start()

    def __enter__(self) -> Px4Autopilot:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- state ------------------------------------------------------------------------------
    @property
    def pid(self) -> int | None:
        return self._process.pid if self._process is not None else None

    @property
    def alive(self) -> bool:
        return self._process is not None and self._process.poll() is None

    @property
    def returncode(self) -> int | None:
        return self._process.poll() if self._process is not None else None

    def tail(self, lines: int = 40) -> str:
        """The last console lines of the current (or last) run."""
        return self._console.tail(lines) if self._console is not None else ""

    def check_alive(self) -> None:
        """Raise Px4Died (with the console tail) if the process has exited."""
        if self._process is None:
            raise Px4Error(f"PX4 instance {self.instance} was not started")
        code = self._process.poll()
        if code is not None:
            if self._console is not None:
                self._console.join(1.0)
            tail = self.tail()
            where = self.console_log if self.config.keep_logs else "console log not kept: pass --run-dir to keep it"
            raise Px4Died(
                f"PX4 instance {self.instance} exited with code {code}; last output ({where}):\n{tail}",
                instance=self.instance, returncode=code, tail=tail,
            )

    def poll(self) -> Px4Observation:
        """Read what PX4 reported (non-blocking) and return the observation."""
        if self._observer is not None:
            self._observer.poll(self.observation)
        if self._console is not None and self._console.ready_for_takeoff:
            self.observation.ready_for_takeoff_line = True
        return self.observation

    @property
    def ready(self) -> bool:
        """PX4 observed ready (see `Px4Observation.ready`); the link is the caller's."""
        return self.poll().ready

    def command(self, command: int, *params: float) -> None:
        """Send a MAVLink COMMAND_LONG over the GCS link (answer in `observation.acks`;
        PX4 only acts on it while simulated time advances)."""
        if self._observer is None:
            raise Px4Error(f"PX4 instance {self.instance} is not running")
        self.observation.acks.pop(command, None)
        self._observer.command(command, *params)


def prune_logs(run_dir: Path, cap_bytes: int) -> None:
    """Delete the oldest PX4 ULog files under `run_dir/px4/*/log` beyond `cap_bytes` total."""
    files = sorted(
        (path for path in Path(run_dir).glob("px4/*/log/**/*.ulg") if path.is_file()),
        key=lambda path: path.stat().st_mtime,
    )
    total = sum(path.stat().st_size for path in files)
    for path in files:
        if total <= cap_bytes:
            break
        total -= path.stat().st_size
        with contextlib.suppress(OSError):
            path.unlink()
