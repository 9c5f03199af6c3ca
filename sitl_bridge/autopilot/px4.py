"""Real PX4 SITL processes as the autopilots of the simulator (`--autopilot px4`).

One `Px4Autopilot` per vehicle instance N runs `px4 -i N -d <rootfs>` (the `bin/px4` of a
`px4_sitl_default` build, its ROMFS `etc` next to it or given) in its own working directory
`<run_dir>/px4/<N>/` with the environment PX4 expects for an external MAVLink simulator:

- `PX4_SIM_MODEL=gazebo-classic_iris` (airframe 10015: rcS then runs
  `simulator_mavlink start -c 4560+N`, so PX4 connects to our `HilLink`);
- `PX4_SIM_SPEED_FACTOR=F` (omitted for F = 0, where rcS would scale timeouts to 0);
- `PX4_HOME_LAT/LON/ALT` from the world's home;
- the overrides of `px4_params/*.params` (format documented there) as `PX4_PARAM_<NAME>`
  (rcS applies them with `param set` early in boot).

rcS rescales a few failsafe timeouts itself when PX4_SIM_SPEED_FACTOR is set, after the
PX4_PARAM_ values (v1.16: x10, x1, x1, x5; older rcS versions used wrong factors, the thesis's
bug; with F = 0 it would set them to 0). So the `wall` timeouts are also checked over MAVLink
once PX4 is up and corrected with PARAM_SET when they differ: what PX4 runs with is observed.

Readiness is observed, never slept for: the simulator link is connected (`HilLink`), and on
PX4's GCS MAVLink port (UDP 18570+N, which we talk to from an ephemeral port, as QGC does)
a HEARTBEAT arrived, SYS_STATUS reports the pre-arm checks passing (or the console printed
"Ready for takeoff!"), a HOME_POSITION was sent (the estimator has a global position) and the
`wall` timeouts read back as configured.

Parameters persisted by PX4 are deleted before each start (every episode starts identical).
PX4's console goes to `console.log` (rotated, capped); a PX4 that dies is reported with the
tail of its output (`Px4Died`). Processes never outlive us: each runs in its own process
group with a parent-death signal, and `stop()`/atexit kill the whole group.
"""

from __future__ import annotations

import atexit
import collections
import contextlib
import ctypes
import fcntl
import logging
import math
import os
import re
import shutil
import signal
import socket
import struct
import subprocess
import threading
import time
import weakref
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sitl_bridge import mavlink
from sitl_bridge.errors import ConfigError
from sitl_bridge.hil.errors import HilError

log = logging.getLogger(__name__)

DEFAULT_AIRFRAME = "gazebo-classic_iris"
GCS_BASE_PORT = 18570
HIL_BASE_PORT = 4560
# Speed factor assumed for `wall` timeouts when F = 0 ("as fast as possible").
MAX_SPEED_ASSUMED = 30.0
DEFAULT_LOG_CAP_BYTES = 20 * 1024 * 1024
PARAMS_DIR = Path(__file__).resolve().parents[2] / "px4_params"
READY_LINE = "Ready for takeoff"
MAV_SYS_STATUS_PREARM_CHECK = 0x10000000


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


# -- parameters ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class Px4Param:
    """One override line: `NAME VALUE [wall [MAX]]` (see px4_params/offboard.params)."""

    name: str
    value: float | int
    wall: bool = False
    maximum: float | None = None

    def resolved(self, speed_factor: float) -> float | int:
        """The value PX4 gets: wall-clock timeouts scaled by the effective speed factor."""
        if not self.wall:
            return self.value
        factor = speed_factor if speed_factor > 0 else MAX_SPEED_ASSUMED
        value = float(self.value) * factor
        return min(value, self.maximum) if self.maximum is not None else value


_NAME = re.compile(r"^[A-Z][A-Z0-9_]{0,15}$")


def _number(text: str) -> float | int:
    return int(text) if re.fullmatch(r"[-+]?\d+", text) else float(text)


def read_params(path: str | os.PathLike[str]) -> list[Px4Param]:
    """Parse a `.params` override file; a bad line is a ConfigError naming file and line."""
    source = str(path)
    try:
        lines = Path(path).read_text().splitlines()
    except OSError as exc:
        raise ConfigError(f"{source}: cannot read file ({exc.strerror})") from None
    params = []
    for number, raw in enumerate(lines, start=1):
        fields = raw.split("#", 1)[0].split()
        if not fields:
            continue
        where = f"{source}: line {number}"
        if not _NAME.match(fields[0]):
            raise ConfigError(f"{where}: expected a PX4 parameter name, got {fields[0]!r}")
        try:
            value = _number(fields[1]) if len(fields) > 1 else None
            maximum = float(fields[3]) if len(fields) > 3 else None
        except ValueError:
            value = None
        wall = len(fields) > 2 and fields[2] == "wall"
        if value is None or len(fields) > 4 or (len(fields) > 2 and not wall):
            raise ConfigError(f"{where}: expected `NAME VALUE [wall [MAX]]`, got {raw.strip()!r}")
        params.append(Px4Param(fields[0], value, wall, maximum))
    return params


def load_param_overrides(
    params_dir: str | os.PathLike[str] | None = None,
    extra: Mapping[str, float | int] | None = None,
) -> dict[str, Px4Param]:
    """All overrides of `params_dir/*.params` (name order, later wins) plus `extra`."""
    directory = Path(params_dir) if params_dir else PARAMS_DIR
    files = sorted(directory.glob("*.params"))
    if not files:
        # Never start PX4 silently without its offboard/failsafe overrides.
        raise ConfigError(f"{directory}: no *.params files (PX4 parameter overrides) found")
    merged: dict[str, Px4Param] = {}
    for path in files:
        for param in read_params(path):
            merged[param.name] = param
    for name, value in (extra or {}).items():
        merged[name] = Px4Param(name, value)
    return merged


def _format(value: float | int) -> str:
    return str(value) if isinstance(value, int) else f"{value:.6g}"


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


# -- MAVLink observation ------------------------------------------------------------------------------
@dataclass
class Px4Observation:
    """What PX4 told us on its GCS MAVLink port (and console) since the last start."""

    heartbeat: bool = False
    armed: bool = False
    custom_mode: int = 0
    prearm_ok: bool = False
    home_ok: bool = False
    ready_for_takeoff_line: bool = False
    params_pending: tuple[str, ...] = ()  # `wall` parameters not yet confirmed
    position_ned_m: tuple[float, float, float] | None = None  # PX4's estimate (LOCAL_POSITION_NED)
    velocity_ned_m_s: tuple[float, float, float] | None = None
    acks: dict[int, int] = field(default_factory=dict)  # command -> MAV_RESULT

    @property
    def ready(self) -> bool:
        """Heartbeat seen, pre-arm checks passing (estimator healthy), home position set, the
        `wall` timeouts confirmed."""
        return (
            self.heartbeat and self.home_ok and not self.params_pending
            and (self.prearm_ok or self.ready_for_takeoff_line)
        )


_PARAM_FLOAT = struct.Struct("<f")
_PARAM_INT = struct.Struct("<i")


class _GcsObserver:
    """A UDP socket talking to PX4's GCS link port: heartbeats out (so PX4 streams to us),
    HEARTBEAT / SYS_STATUS / HOME_POSITION in; reads back parameters that must hold a value
    and sets them (PARAM_SET, PX4's bytewise int encoding) when they differ."""

    RESEND_S = 0.5

    def __init__(self, instance: int, host: str, enforce: Mapping[str, float | int]) -> None:
        self.target = (host, GCS_BASE_PORT + instance)
        self.target_system = (instance + 1) & 0xFF
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((host, 0))
        self.sock.setblocking(False)
        self._codec = mavlink.new_codec(255, 190)  # QGC's ids
        self._last_send = 0.0
        self._enforce = dict(enforce)
        self._types: dict[str, int] = {}

    def _send(self, message: mavlink.MAVLinkMessage) -> None:
        with contextlib.suppress(OSError):  # PX4 not listening yet
            self.sock.sendto(bytes(message.pack(self._codec)), self.target)

    def _send_requests(self) -> None:
        dialect = mavlink.dialect
        self._send(dialect.MAVLink_heartbeat_message(
            dialect.MAV_TYPE_GCS, dialect.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3))
        for name, value in self._enforce.items():
            param_type = self._types.get(name)
            if param_type is None:
                self._send(dialect.MAVLink_param_request_read_message(
                    self.target_system, 1, name.encode(), -1))
                continue
            if param_type == dialect.MAV_PARAM_TYPE_INT32:
                wire = _PARAM_FLOAT.unpack(_PARAM_INT.pack(int(round(value))))[0]
            else:
                wire = float(value)
            self._send(dialect.MAVLink_param_set_message(
                self.target_system, 1, name.encode(), wire, param_type))

    def _param_value(self, msg: Any, obs: Px4Observation) -> None:
        name = msg.param_id.rstrip("\0") if isinstance(msg.param_id, str) else msg.param_id
        if name not in self._enforce:
            return
        if msg.param_type == mavlink.dialect.MAV_PARAM_TYPE_INT32:
            value: float = _PARAM_INT.unpack(_PARAM_FLOAT.pack(msg.param_value))[0]
        else:
            value = msg.param_value
        wanted = self._enforce[name]
        if abs(value - wanted) <= 1e-4 * max(1.0, abs(wanted)):
            del self._enforce[name]
            obs.params_pending = tuple(self._enforce)
            log.debug("PX4 sys %d: %s = %s confirmed", self.target_system, name, value)
        else:
            log.info("PX4 sys %d: %s is %s, setting %s", self.target_system, name, value, wanted)
            self._types[name] = msg.param_type
            self._last_send = 0.0  # set it now

    def poll(self, obs: Px4Observation) -> None:
        now = time.monotonic()
        if now - self._last_send >= self.RESEND_S:
            self._last_send = now
            self._send_requests()
        while True:
            try:
                data = self.sock.recv(65536)
            except OSError:  # nothing more (or PX4 not up yet: connection refused)
                return
            for frame in mavlink.FrameParser().feed(data):
                if frame.component_id != 1:
                    continue
                msgid = frame.msgid
                if msgid == mavlink.HEARTBEAT:
                    msg = mavlink.decode_frame(self._codec, frame)
                    obs.heartbeat = True
                    obs.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                    obs.custom_mode = msg.custom_mode
                elif msgid == mavlink.dialect.MAVLINK_MSG_ID_SYS_STATUS:
                    msg = mavlink.decode_frame(self._codec, frame)
                    obs.prearm_ok = bool(msg.onboard_control_sensors_health & MAV_SYS_STATUS_PREARM_CHECK)
                elif msgid == mavlink.dialect.MAVLINK_MSG_ID_HOME_POSITION:
                    obs.home_ok = True
                elif msgid == mavlink.dialect.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
                    _t, x, y, z, vx, vy, vz = mavlink.unpack_payload(frame)
                    obs.position_ned_m = (x, y, z)
                    obs.velocity_ned_m_s = (vx, vy, vz)
                elif msgid == mavlink.dialect.MAVLINK_MSG_ID_COMMAND_ACK:
                    msg = mavlink.decode_frame(self._codec, frame)
                    obs.acks[msg.command] = msg.result
                elif msgid == mavlink.dialect.MAVLINK_MSG_ID_PARAM_VALUE:
                    self._param_value(mavlink.decode_frame(self._codec, frame), obs)

    def command(self, command: int, *params: float) -> None:
        """Send COMMAND_LONG to the autopilot (as a GCS would)."""
        values = [float(p) for p in params] + [0.0] * (7 - len(params))
        self._send(mavlink.dialect.MAVLink_command_long_message(
            self.target_system, 1, command, 0, *values))

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.close()


# -- one PX4 process -------------------------------------------------------------------------------
_LIVE: weakref.WeakSet[Px4Autopilot] = weakref.WeakSet()


def _stop_all_at_exit() -> None:
    for autopilot in list(_LIVE):
        with contextlib.suppress(Exception):
            autopilot.stop(timeout_s=2.0)


atexit.register(_stop_all_at_exit)


try:  # loaded here, not in the forked child (no imports or locks between fork and exec)
    _LIBC: Any = ctypes.CDLL(None, use_errno=True)
except OSError:  # pragma: no cover - not Linux
    _LIBC = None
_PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:
    """Runs in the child before exec: the kernel SIGKILLs PX4 if we die without cleaning up."""
    if _LIBC is not None:
        _LIBC.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)


class Px4Autopilot:
    """One PX4 SITL process for vehicle `instance` (see module docstring).

    Start it from a thread that lives as long as PX4 should (normally the main thread): the
    parent-death signal fires when the starting thread ends.
    """

    def __init__(self, config: Px4Config, instance: int) -> None:
        if not 0 <= instance <= 254:
            raise Px4Error(f"PX4 instance must be in 0..254 (MAV_SYS_ID = instance + 1), got {instance}")
        self.config = config
        self.instance = instance
        self.work_dir = config.run_dir / "px4" / str(instance)
        self.console_log = self.work_dir / "console.log"
        self.observation = Px4Observation()
        self.starts = 0
        self._process: subprocess.Popen[bytes] | None = None
        self._console: _Console | None = None
        self._observer: _GcsObserver | None = None

    # -- lifecycle ------------------------------------------------------------------------
    def environment(self) -> dict[str, str]:
        """The environment PX4 is started with."""
        config = self.config
        env = dict(os.environ)
        for key in list(env):
            if key.startswith("PX4_PARAM_") or key in ("PX4_SYS_AUTOSTART", "PX4_SIM_SPEED_FACTOR"):
                del env[key]  # only what this configuration says
        env["PX4_SIM_MODEL"] = config.airframe
        if config.speed_factor > 0:
            env["PX4_SIM_SPEED_FACTOR"] = _format(config.speed_factor)
        env["PX4_HOME_LAT"] = f"{config.home_lat_deg:.9f}"
        env["PX4_HOME_LON"] = f"{config.home_lon_deg:.9f}"
        env["PX4_HOME_ALT"] = f"{config.home_alt_m:.3f}"
        if config.sim_host not in ("127.0.0.1", "localhost"):
            env["PX4_SIM_HOST_ADDR"] = config.sim_host
        for name, value in config.resolved_params().items():
            env[f"PX4_PARAM_{name}"] = _format(value)
        return env

    def _prepare_work_dir(self) -> None:
        self.work_dir.mkdir(parents=True, exist_ok=True)
        # Parameters PX4 saved last time would override the airframe and our overrides.
        for stale in ("parameters.bson", "parameters_backup.bson", "dataman"):
            with contextlib.suppress(FileNotFoundError):
                (self.work_dir / stale).unlink()
        shutil.rmtree(self.work_dir / "eeprom", ignore_errors=True)
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
            preexec_fn=_die_with_parent,
        )
        self.starts += 1
        _LIVE.add(self)
        self._console = _Console(self._process.stdout, self.console_log, self.config.log_cap_bytes)
        self._observer = _GcsObserver(self.instance, "127.0.0.1", wall)

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
            raise Px4Died(
                f"PX4 instance {self.instance} exited with code {code}; last output "
                f"({self.console_log}):\n{tail}",
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


# -- several vehicles with the lockstep --------------------------------------------------------------
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

