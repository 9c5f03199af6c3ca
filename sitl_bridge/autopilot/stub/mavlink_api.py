"""PX4's MAVLink API for the stub, on UDP: what MAVSDK, QGroundControl and MAVProxy talk to.

Two links per vehicle instance i, like PX4 SITL's `px4-rc.mavlink`: the offboard/API link
(bind 127.0.0.1:14580+i, send to 14540+i) and a GCS link (bind 18570+i, send to 14550).
A link keeps its client like PX4's `mavlink_receiver` keeps its partner: telemetry goes to the
configured remote port until a valid frame arrives, then to the first address that sent one.
Frames from any other address are still handled and answered at that address (acks,
parameters, requested messages), but they do not redirect the telemetry. Handover: once the
client has sent no valid frame for `CLIENT_TIMEOUT_WALL_S` (2.5 s of wall time, PX4's heartbeat
timeout; MAVSDK sends a heartbeat every second), the next sender becomes the client.

Telemetry streams run on SIMULATED time (the autopilot's clock); only the keep-alive HEARTBEAT
looks at the wall clock: MAVSDK drops a vehicle after 3 s of wall time without one, and while
the simulation is held simulated time stands still.

`pump()` never blocks: it reads every waiting datagram, handles it, and sends what is due.
Garbage datagrams are counted in `stats` and ignored.

Batched telemetry (`batch_wall_s` > 0, for an in-process stub pumped by the lockstep): while
simulated time runs, the streams' messages queue up and go out in one datagram per link every
`batch_wall_s` of wall time (or every `BATCH_MAX_MESSAGES`), not one datagram per step: each
datagram wakes the client's receiving thread (MAVSDK), which on a busy machine costs the
lockstep its CPU. The GCS link, a display for people (its streams are 1-20 Hz), batches over
`GCS_BATCH_FACTOR` times as long: it carries a sixth of the messages, but with the same interval
sent as many datagrams as the API link (often to a port nobody listens on). A pump at unchanged
simulated time (held: the lockstep's `hold()` and `idle()`) sends everything queued, so a
client reading while the simulation is held sees the same telemetry as without batching. Answers (acks, parameters) always go out at once.
While batching and running, the sockets are also read at most every `POLL_WALL_S` of wall time
(one `poll` syscall per step otherwise, at thousands of steps per second); a held pump always
reads them.
"""

from __future__ import annotations

import contextlib
import logging
import math
import select
import socket
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from sitl_bridge import mavlink
from sitl_bridge.ports import (
    API_BIND_BASE_PORT,
    API_CLIENT_BASE_PORT,
    GCS_BIND_BASE_PORT,
    GCS_REMOTE_PORT,
)

from . import telemetry
from .fence import REACH_M, Fence
from .modes import CommandResult, system_id_for
from .param_bounds import clamp_to_px4_range
from .params import MAV_PARAM_TYPE_INT32, MAV_PARAM_TYPE_REAL32, Param, decode_param_value
from .telemetry import MessagePacker
from .vec import quat_rotate, wrap_pi

if TYPE_CHECKING:
    from .autopilot import StubAutopilot

log = logging.getLogger(__name__)
d = mavlink.dialect

API_REMOTE_BASE_PORT = API_CLIENT_BASE_PORT  # the stub's name for it
KEEPALIVE_WALL_S = 1.0
CLIENT_TIMEOUT_WALL_S = 2.5  # client silence after which another sender takes the link (PX4's heartbeat timeout)
BATCH_MAX_MESSAGES = 20  # per datagram: well under UDP size limits
GCS_BATCH_FACTOR = 10  # the GCS link's batch interval, in API link intervals (20 ms wall in-process)
POLL_WALL_S = 0.0005  # batched and running: read the sockets at most this often (wall)
FORCE_DISARM_MAGIC = 21196

# SET_POSITION_TARGET_LOCAL_NED type_mask bits (POSITION_TARGET_TYPEMASK)
_IGNORE_POS = 0x7
_IGNORE_VEL = 0x38
_IGNORE_ACC = 0x1C0
_IGNORE_YAW = 0x400
_IGNORE_YAW_RATE = 0x800
_NAN = float("nan")

_CMD_STRUCT_LONG = d.MAVLink_command_long_message.unpacker
_CMD_STRUCT_INT = d.MAVLink_command_int_message.unpacker
_PARAM_VALUE_TAIL = struct.Struct("<HH16sB")   # PARAM_VALUE after param_value
_EARTH_RADIUS_M = 6378137.0
# commands whose acceptance changes what HEARTBEAT says (armed flag, mode)
_STATE_COMMANDS = frozenset((
    d.MAV_CMD_COMPONENT_ARM_DISARM, d.MAV_CMD_NAV_TAKEOFF, d.MAV_CMD_NAV_LAND, d.MAV_CMD_NAV_RETURN_TO_LAUNCH,
    d.MAV_CMD_DO_SET_MODE, d.MAV_CMD_DO_REPOSITION,
))


def _int_param(value: float) -> int | None:
    """A command parameter as an int; None when NaN or infinite (not given)."""
    return int(value) if value == value and abs(value) != math.inf else None


@dataclass
class ApiStats:
    """Counters since construction (all links)."""

    datagrams: int = 0
    frames: int = 0
    garbage_datagrams: int = 0     # datagrams without a single valid frame
    garbage_bytes: int = 0
    bad_crc: int = 0
    commands: int = 0
    unsupported_commands: int = 0
    setpoints: int = 0
    param_sets: int = 0
    sent_datagrams: int = 0
    send_errors: int = 0
    keepalives: int = 0
    ignored_messages: dict[int, int] = field(default_factory=dict)


class _Link:
    """One UDP socket, its peer and its stream schedule (intervals in us of simulated time)."""

    def __init__(self, name: str, host: str, bind_port: int, remote: tuple[str, int],
                 rates_hz: dict[int, float], batch_wall_s: float = 0.0) -> None:
        self.name = name
        self.batch_wall_s = batch_wall_s  # see MavlinkApi (batched telemetry)
        self.last_flush_wall = -math.inf
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.bind((host, bind_port))
        except OSError:
            self.sock.close()
            raise
        self.sock.setblocking(False)
        self.remote = remote           # where telemetry goes: the configured port, then the client
        self.client: tuple[str, int] | None = None   # the first sender of a valid frame (see module docstring)
        self.client_heard_wall = -math.inf
        self.intervals_us = {msgid: int(round(1e6 / hz)) for msgid, hz in rates_hz.items() if hz > 0}
        self.default_intervals_us = dict(self.intervals_us)
        self.next_due_us: dict[int, int] = {}
        self.next_due_any_us = -1  # earliest of next_due_us (-1: scan at the next step)
        self.outbox: list[bytes] = []

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.close()


class MavlinkApi:
    """Serves one StubAutopilot's MAVLink API on UDP (see module docstring).

    instance: vehicle instance i (ports 14580+i -> 14540+i, 18570+i -> 14550); defaults to
        the autopilot's instance.
    host: address to bind and to send to (127.0.0.1 by default).
    gcs: also serve the GCS link.
    api_streams: the API link's streams, a `telemetry.API_STREAMS` name: "onboard" (the usual
        set) or "client" (only what `sitl_bridge.client` reads).
    clock: wall clock for the keep-alive and the batching (time.monotonic; injectable for tests).
    batch_wall_s: batch the streams' messages over this much wall time while simulated time
        runs (0: one datagram per pump, for a stub whose pumps may stop without a final one).
    fence: the world's workspace, where DO_REPOSITION may send the vehicle (`fence.py`; None:
        only the `REACH_M` bound).
    """

    def __init__(self, autopilot: StubAutopilot, instance: int | None = None, host: str = "127.0.0.1", *,
                 api_bind_port: int | None = None, api_remote_port: int | None = None, gcs: bool = True,
                 gcs_bind_port: int | None = None, gcs_remote_port: int = GCS_REMOTE_PORT,
                 keepalive_wall_s: float = KEEPALIVE_WALL_S, clock: Callable[[], float] = time.monotonic,
                 batch_wall_s: float = 0.0, api_streams: str = "onboard", fence: Fence | None = None) -> None:
        if api_streams not in telemetry.API_STREAMS:
            raise ValueError(f"api_streams: expected one of {', '.join(telemetry.API_STREAMS)}, got {api_streams!r}")
        self.autopilot = autopilot
        self.fence = fence
        self.instance = autopilot.instance if instance is None else instance
        self.system_id = system_id_for(self.instance)
        self.component_id = 1
        self.stats = ApiStats()
        self._packer = MessagePacker(self.system_id, self.component_id)
        self._clock = clock
        self._keepalive_wall_s = keepalive_wall_s
        self.batch_wall_s = batch_wall_s
        i = self.instance
        self.links: list[_Link] = []
        try:
            self.links.append(_Link(
                "api", host, api_bind_port if api_bind_port is not None else API_BIND_BASE_PORT + i,
                (host, api_remote_port if api_remote_port is not None else API_REMOTE_BASE_PORT + i),
                telemetry.API_STREAMS[api_streams], batch_wall_s))
            if gcs:
                self.links.append(_Link(
                    "gcs", host, gcs_bind_port if gcs_bind_port is not None else GCS_BIND_BASE_PORT + i,
                    (host, gcs_remote_port), telemetry.GCS_RATES_HZ, batch_wall_s * GCS_BATCH_FACTOR))
        except OSError:
            self.close()
            raise
        self._last_stream_time_us: int | None = None
        self._next_due_any_us = -1        # earliest stream deadline over all links
        self._poll: select.poll | None = None
        self._last_poll_wall = -math.inf
        self._link_by_fd: dict[int, _Link] = {}
        self._last_heartbeat_wall = -math.inf
        self._texts_sent = 0
        self._handlers: dict[int, Callable[[_Link, mavlink.Frame, tuple[str, int]], None]] = {
            d.MAVLINK_MSG_ID_HEARTBEAT: lambda *_: None,
            d.MAVLINK_MSG_ID_COMMAND_LONG: self._on_command_long,
            d.MAVLINK_MSG_ID_COMMAND_INT: self._on_command_int,
            d.MAVLINK_MSG_ID_PARAM_REQUEST_LIST: self._on_param_request_list,
            d.MAVLINK_MSG_ID_PARAM_REQUEST_READ: self._on_param_request_read,
            d.MAVLINK_MSG_ID_PARAM_SET: self._on_param_set,
            d.MAVLINK_MSG_ID_SET_POSITION_TARGET_LOCAL_NED: self._on_set_position_target_local_ned,
            d.MAVLINK_MSG_ID_TIMESYNC: self._on_timesync,
        }

    # --- lifecycle ------------------------------------------------------------------------------
    @property
    def ports(self) -> dict[str, int]:
        """Bound local port per link name."""
        return {link.name: link.sock.getsockname()[1] for link in self.links}

    def filenos(self) -> list[int]:
        """Socket descriptors (for select in a blocking loop)."""
        return [link.sock.fileno() for link in self.links]

    def close(self) -> None:
        """Close every socket (frees the ports)."""
        for link in self.links:
            link.close()
        self.links = []

    def __enter__(self) -> MavlinkApi:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- pump -----------------------------------------------------------------------------------
    def pump(self) -> None:
        """Read and handle every waiting datagram, then send the streams that are due."""
        running = self.autopilot.time_us != self._last_stream_time_us
        batching = running and self.batch_wall_s > 0.0
        wall = self._clock()
        if not batching or wall - self._last_poll_wall >= POLL_WALL_S:
            self._last_poll_wall = wall
            self._read_sockets()
        self._send_streams(wall)
        for link in self.links:
            outbox = link.outbox
            if not outbox:
                continue
            if batching and wall - link.last_flush_wall < link.batch_wall_s and len(outbox) < BATCH_MAX_MESSAGES:
                continue  # batched: see the module docstring
            link.last_flush_wall = wall
            self._flush(link)

    def _read_sockets(self) -> None:
        """Handle every waiting datagram (one poll syscall, not a failing recv per socket)."""
        if self._poll is None:
            self._poll = select.poll()
            self._link_by_fd = {link.sock.fileno(): link for link in self.links}
            for fd in self._link_by_fd:
                self._poll.register(fd, select.POLLIN)
        for fd, _events in self._poll.poll(0):
            link = self._link_by_fd.get(fd)
            if link is not None:
                self._receive(link)

    def _receive(self, link: _Link) -> None:
        sock = link.sock
        while True:
            try:
                data, address = sock.recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                return
            except ConnectionRefusedError:
                continue  # ICMP port unreachable from an earlier send: nobody listening yet
            except OSError as exc:
                log.debug("%s link receive error: %s", link.name, exc)
                return
            self.stats.datagrams += 1
            parser = mavlink.FrameParser()
            frames = parser.feed(data)
            self.stats.garbage_bytes += parser.stats.garbage_bytes
            self.stats.bad_crc += parser.stats.bad_crc
            if not frames:
                self.stats.garbage_datagrams += 1
                continue
            if not self._from_client(link, address):
                self._flush(link)  # queued telemetry is the client's; answers go to the sender
            for frame in frames:
                self.stats.frames += 1
                handler = self._handlers.get(frame.msgid)
                if handler is None:
                    ignored = self.stats.ignored_messages
                    ignored[frame.msgid] = ignored.get(frame.msgid, 0) + 1
                    continue
                try:
                    handler(link, frame, address)
                except Exception:  # a malformed message must not kill the vehicle
                    log.exception("%s link: error handling message %d", link.name, frame.msgid)

    def _from_client(self, link: _Link, address: tuple[str, int]) -> bool:
        """Whether a valid frame from `address` comes from the link's client; the first sender
        becomes the client, and any sender once the client has been silent for the timeout."""
        wall = self._clock()
        if address != link.client:
            if link.client is not None and wall - link.client_heard_wall < CLIENT_TIMEOUT_WALL_S:
                return False
            if link.client is not None:
                log.info("%s link: client %s:%d silent for %.1f s; now serving %s:%d", link.name,
                         *link.client, wall - link.client_heard_wall, *address)
            link.client = link.remote = address
        link.client_heard_wall = wall
        return True

    def _flush(self, link: _Link, to: tuple[str, int] | None = None) -> None:
        """Send the queued messages in one datagram to `to` (default: the link's client)."""
        if not link.outbox:
            return
        data = b"".join(link.outbox)
        link.outbox.clear()
        try:
            link.sock.sendto(data, to or link.remote)
            self.stats.sent_datagrams += 1
        except (BlockingIOError, ConnectionRefusedError, InterruptedError):
            self.stats.send_errors += 1
        except OSError as exc:
            self.stats.send_errors += 1
            log.debug("%s link send error: %s", link.name, exc)

    def _queue(self, link: _Link, cls: type, fields: dict) -> None:
        link.outbox.append(self._packer.pack_fields(cls, fields))

    def send_now(self, msgid: int, link: _Link | None = None, built: dict[int, dict | None] | None = None) -> bool:
        """Queue one message (a BUILDERS id) on one or all links; False when it has no data yet.
        `built`: fields already built at this step, by message id (filled in here)."""
        entry = telemetry.BUILDERS.get(msgid)
        if entry is None:
            return False
        cls, build = entry
        if built is None:
            fields = build(self.autopilot)
        elif msgid in built:
            fields = built[msgid]
        else:
            fields = built[msgid] = build(self.autopilot)
        if fields is None:
            return False
        for target in [link] if link is not None else self.links:
            self._queue(target, cls, fields)
        return True

    def _send_streams(self, wall: float) -> None:
        now_us = self.autopilot.time_us
        last = self._last_stream_time_us
        texts = self.autopilot.commander.status_texts
        if now_us != last and (now_us >= self._next_due_any_us or last is None or now_us < last or texts):
            self._last_stream_time_us = now_us
            next_any = now_us + 10**9
            restart = last is None or now_us < last
            built: dict[int, dict | None] = {}   # a message due on both links is built once
            for link in self.links:
                if now_us < link.next_due_any_us and not restart:
                    next_any = min(next_any, link.next_due_any_us)
                    continue  # nothing due on this link: skip its schedule
                self._send_due(link, now_us, wall, built)
                link.next_due_any_us = min(link.next_due_us.values()) if link.next_due_us else now_us + 10**9
                next_any = min(next_any, link.next_due_any_us)
            self._next_due_any_us = next_any
            self._send_status_texts()
        elif now_us != last:
            self._last_stream_time_us = now_us
        if wall - self._last_heartbeat_wall >= self._keepalive_wall_s:
            # simulated time is frozen (or crawling): keep MAVSDK's 3 s wall timeout at bay
            self.send_now(d.MAVLINK_MSG_ID_HEARTBEAT)
            self._last_heartbeat_wall = wall
            self.stats.keepalives += 1

    def _send_due(self, link: _Link, now_us: int, wall: float, built: dict[int, dict | None]) -> None:
        """Queue every stream of `link` due at `now_us` and schedule its next time."""
        due = link.next_due_us
        for msgid, interval in link.intervals_us.items():
            t = due.get(msgid)
            if t is not None and now_us < t <= now_us + interval:
                continue  # not due yet
            # stay on a fixed grid; after a gap or a clock reset start a new one
            on_grid = t is not None and 0 <= now_us - t < interval
            due[msgid] = t + interval if on_grid else now_us + interval
            if self.send_now(msgid, link, built) and msgid == d.MAVLINK_MSG_ID_HEARTBEAT:
                self._last_heartbeat_wall = wall

    def _send_status_texts(self) -> None:
        texts = self.autopilot.commander.status_texts
        for severity, text in list(texts):
            for link in self.links:
                self._queue(link, d.MAVLink_statustext_message,
                            dict(severity=severity, text=text.encode()[:50]))
        texts.clear()

    # --- incoming -------------------------------------------------------------------------------
    def _for_us(self, target_system: int, target_component: int) -> bool:
        return target_system in (0, self.system_id) and target_component in (0, self.component_id)

    def _ack(self, link: _Link, frame: mavlink.Frame, command: int, result: int, to: tuple[str, int]) -> None:
        self._queue(link, d.MAVLink_command_ack_message,
                    dict(command=command, result=int(result), target_system=frame.system_id,
                         target_component=frame.component_id))
        self._flush(link, to)

    def _on_command_long(self, link: _Link, frame: mavlink.Frame, address: tuple[str, int]) -> None:
        p1, p2, p3, p4, p5, p6, p7, command, ts, tc, _confirmation = _CMD_STRUCT_LONG.unpack(frame.payload)
        if not self._for_us(ts, tc):
            return
        # COMMAND_LONG carries positions as degrees (params 5, 6) and altitude AMSL (param 7)
        self._command(link, frame, address, command, (p1, p2, p3, p4, p5, p6, p7), relative_alt=False)

    def _on_command_int(self, link: _Link, frame: mavlink.Frame, address: tuple[str, int]) -> None:
        p1, p2, p3, p4, x, y, z, command, ts, tc, coord_frame, _cur, _auto = _CMD_STRUCT_INT.unpack(frame.payload)
        if not self._for_us(ts, tc):
            return
        relative = coord_frame in (d.MAV_FRAME_GLOBAL_RELATIVE_ALT, d.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT)
        # x, y are degE7; INT32_MAX means "unchanged" like a NaN param
        lat = x * 1e-7 if x != 2**31 - 1 else _NAN
        lon = y * 1e-7 if y != 2**31 - 1 else _NAN
        self._command(link, frame, address, command, (p1, p2, p3, p4, lat, lon, z), relative_alt=relative)

    def _command(self, link: _Link, frame: mavlink.Frame, address: tuple[str, int], command: int,
                 p: tuple[float, ...], *, relative_alt: bool) -> None:
        """Execute, ACK from compid 1 (always: MAVSDK retries and times out otherwise), then send
        what the command asked for and a HEARTBEAT so a state change shows at once."""
        self.stats.commands += 1
        try:
            result, reply_msgid = self._execute(link, command, p, relative_alt)
        except Exception:   # a malformed command must not kill the vehicle
            log.exception("%s link: command %d failed", link.name, command)
            result, reply_msgid = CommandResult.FAILED, None
        if result == CommandResult.UNSUPPORTED:
            self.stats.unsupported_commands += 1
        self._ack(link, frame, command, result, address)
        if reply_msgid is not None and not self.send_now(reply_msgid, link):
            log.debug("requested message %d has no data yet", reply_msgid)
        if result == CommandResult.ACCEPTED and reply_msgid is None and command in _STATE_COMMANDS:
            self.send_now(d.MAVLINK_MSG_ID_HEARTBEAT, link)
        self._flush(link, address)

    def _execute(self, link: _Link, command: int, p: tuple[float, ...],
                 relative_alt: bool) -> tuple[CommandResult, int | None]:
        """(result, message id to send after the ACK or None)."""
        ap = self.autopilot
        if command == d.MAV_CMD_COMPONENT_ARM_DISARM:
            # like PX4: 1 arms, 0 disarms, anything else is refused; 21196 in param 2 forces
            if p[0] == 1.0:
                return ap.arm(), None
            if p[0] == 0.0:
                return ap.disarm(force=p[1] == FORCE_DISARM_MAGIC), None
            return CommandResult.DENIED, None
        if command == d.MAV_CMD_NAV_TAKEOFF:
            return ap.takeoff(), None
        if command == d.MAV_CMD_NAV_LAND:
            return ap.land(), None
        if command == d.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return ap.return_to_launch(), None
        if command == d.MAV_CMD_DO_SET_MODE:
            base_mode, main_mode, sub_mode = _int_param(p[0]), _int_param(p[1]), _int_param(p[2])
            if base_mode is None or not base_mode & d.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED or main_mode is None:
                return CommandResult.UNSUPPORTED, None
            return ap.set_mode(main_mode & 0xFF, (sub_mode or 0) & 0xFF), None
        if command == d.MAV_CMD_DO_REPOSITION:
            return self._reposition(p, relative_alt), None
        if command == d.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self._set_message_interval(link, p[0], p[1]), None
        if command == d.MAV_CMD_REQUEST_MESSAGE:
            msgid = _int_param(p[0])
            if msgid in telemetry.BUILDERS:
                return CommandResult.ACCEPTED, msgid
            return CommandResult.DENIED, None
        if command == d.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            return CommandResult.ACCEPTED, d.MAVLINK_MSG_ID_AUTOPILOT_VERSION
        if command == d.MAV_CMD_GET_HOME_POSITION:
            if ap.home is None:
                return CommandResult.TEMPORARILY_REJECTED, None
            return CommandResult.ACCEPTED, d.MAVLINK_MSG_ID_HOME_POSITION
        return CommandResult.UNSUPPORTED, None

    def _reposition(self, p: tuple[float, ...], relative_alt: bool) -> CommandResult:
        """DO_REPOSITION (MAVSDK goto_location, QGC "fly here"): hold at a new global position."""
        est = self.autopilot.estimate
        if est.origin is None:
            return CommandResult.TEMPORARILY_REJECTED
        lat0, lon0, alt0 = est.origin
        cur = est.position_ned_m
        lat, lon, alt = p[4], p[5], p[6]
        # Like PX4's navigator: a non-finite field (NaN, +-inf) means "keep the current value";
        # a latitude or longitude outside the globe is refused.
        if (math.isfinite(lat) and abs(lat) > 90.0) or (math.isfinite(lon) and abs(lon) > 180.0):
            return CommandResult.DENIED
        north = math.radians(lat - lat0) * _EARTH_RADIUS_M if math.isfinite(lat) else cur[0]
        east = (math.radians(lon - lon0) * _EARTH_RADIUS_M * math.cos(math.radians(lat0))
                if math.isfinite(lon) else cur[1])
        if math.isfinite(alt):
            home = self.autopilot.home
            alt_amsl = alt + (home.alt_amsl_m if home is not None else alt0) if relative_alt else alt
            down = alt0 - alt_amsl
        else:
            down = cur[2]
        yaw = wrap_pi(math.radians(p[3])) if math.isfinite(p[3]) else None
        refusal = self._reposition_refusal(north, east, down)
        if refusal is not None:
            self.autopilot.commander.status_texts.append((d.MAV_SEVERITY_WARNING, f"Reposition refused: {refusal}"))
            log.info("DO_REPOSITION to (%g, %g, %g) m NED refused: %s", north, east, down, refusal)
            return CommandResult.DENIED
        return self.autopilot.reposition((north, east, down), yaw)

    def _reposition_refusal(self, north: float, east: float, down: float) -> str | None:
        """Why a reposition target (local NED around the estimator's origin) is refused, or None."""
        if max(abs(north), abs(east), abs(down)) > REACH_M:
            return f"target over {REACH_M / 1000:g} km away"
        if self.fence is None:
            return None
        lat0, lon0, alt0 = self.autopilot.estimate.origin  # type: ignore[misc] (checked by the caller)
        lat = lat0 + math.degrees(north / _EARTH_RADIUS_M)
        lon = lon0 + math.degrees(east / (_EARTH_RADIUS_M * math.cos(math.radians(lat0))))
        return "outside the workspace" if self.fence.outside(lat, lon, alt0 - down) else None

    def _set_message_interval(self, link: _Link, msgid_f: float, interval_f: float) -> CommandResult:
        if not math.isfinite(msgid_f) or int(msgid_f) not in telemetry.BUILDERS:
            return CommandResult.DENIED
        if interval_f != interval_f:
            interval_f = 0.0  # NaN: not given, the default rate
        if not math.isfinite(interval_f) and interval_f > 0:
            return CommandResult.DENIED  # +inf: no such interval (-inf: < 0, stop the stream)
        msgid = int(msgid_f)
        interval = -1 if interval_f < 0 else int(interval_f)
        if interval < 0:
            link.intervals_us.pop(msgid, None)
        elif interval == 0:
            default = link.default_intervals_us.get(msgid)
            if default is None:
                link.intervals_us.pop(msgid, None)
            else:
                link.intervals_us[msgid] = default
        else:
            link.intervals_us[msgid] = interval
        link.next_due_us.pop(msgid, None)
        link.next_due_any_us = self._next_due_any_us = -1
        return CommandResult.ACCEPTED

    # parameters ---------------------------------------------------------------------------------
    def _param_value(self, link: _Link, param: Param) -> None:
        # packed by hand so INT32 bits reach the wire untouched (see encode_param_value)
        table = self.autopilot.params
        payload = param.wire_bytes + _PARAM_VALUE_TAIL.pack(
            len(table), table.index_of(param.name), param.name.encode(), param.param_type)
        link.outbox.append(self._packer.encoder.frame(
            d.MAVLINK_MSG_ID_PARAM_VALUE, d.MAVLink_param_value_message.crc_extra, payload))

    def _on_param_request_list(self, link: _Link, frame: mavlink.Frame, address: tuple[str, int]) -> None:
        ts, tc = mavlink.unpack_payload(frame)
        if not self._for_us(ts, tc):
            return
        for param in self.autopilot.params:
            self._param_value(link, param)
            if len(link.outbox) >= 20:   # keep datagrams well under the UDP size limits
                self._flush(link, address)
        self._flush(link, address)

    def _on_param_request_read(self, link: _Link, frame: mavlink.Frame, address: tuple[str, int]) -> None:
        index, ts, tc, raw_id = mavlink.unpack_payload(frame)
        if not self._for_us(ts, tc):
            return
        table = self.autopilot.params
        param = table.at(index) if index >= 0 else table.get(raw_id.split(b"\0", 1)[0].decode(errors="replace"))
        if param is None:
            return  # PX4 stays silent on unknown names; the client times out
        self._param_value(link, param)
        self._flush(link, address)

    def _on_param_set(self, link: _Link, frame: mavlink.Frame, address: tuple[str, int]) -> None:
        _value, ts, tc, raw_id, param_type = mavlink.unpack_payload(frame)
        if not self._for_us(ts, tc):
            return
        table = self.autopilot.params
        param = table.get(raw_id.split(b"\0", 1)[0].decode(errors="replace"))
        if param is None:
            return
        if param_type not in (MAV_PARAM_TYPE_INT32, MAV_PARAM_TYPE_REAL32):
            param_type = param.param_type
        value = decode_param_value(frame.payload, param_type)
        if math.isfinite(value):
            bounded = clamp_to_px4_range(param.name, value)
            if bounded != value:
                log.warning("PARAM_SET %s = %g is outside PX4's range; set to %g", param.name, value, bounded)
            table.set(param.name, bounded)
            self.stats.param_sets += 1
        else:
            log.warning("PARAM_SET %s = %g refused (not finite)", param.name, value)
        self._param_value(link, param)   # echo (the unchanged value when refused)
        self._flush(link, address)

    # offboard setpoints ---------------------------------------------------------------------------
    def _on_set_position_target_local_ned(self, link: _Link, frame: mavlink.Frame, _address) -> None:
        (_t, x, y, z, vx, vy, vz, _afx, _afy, _afz, yaw, yaw_rate, mask, ts, tc,
         coordinate_frame) = mavlink.unpack_payload(frame)
        if not self._for_us(ts, tc):
            return
        ap = self.autopilot
        est = ap.estimate
        position = (x, y, z) if not mask & _IGNORE_POS else (_NAN, _NAN, _NAN)
        velocity = (vx, vy, vz) if not mask & _IGNORE_VEL else (_NAN, _NAN, _NAN)
        if coordinate_frame in (d.MAV_FRAME_BODY_NED, d.MAV_FRAME_BODY_OFFSET_NED):
            # body frames are yaw-rotated (PX4 ignores roll and pitch here)
            yaw_now = est.euler_rad[2]
            half = 0.5 * yaw_now
            q_yaw = (math.cos(half), 0.0, 0.0, math.sin(half))
            velocity = quat_rotate(q_yaw, velocity) if velocity[0] == velocity[0] else velocity
            if position[0] == position[0]:
                position = quat_rotate(q_yaw, position)
        if coordinate_frame in (d.MAV_FRAME_LOCAL_OFFSET_NED, d.MAV_FRAME_BODY_OFFSET_NED) and position[0] == position[0]:
            p = est.position_ned_m
            position = (p[0] + position[0], p[1] + position[1], p[2] + position[2])
        elif coordinate_frame not in (d.MAV_FRAME_LOCAL_NED, d.MAV_FRAME_BODY_NED, d.MAV_FRAME_LOCAL_OFFSET_NED,
                                      d.MAV_FRAME_BODY_OFFSET_NED):
            return
        if position[0] != position[0] and velocity[0] != velocity[0]:
            return  # acceleration-only setpoints are not supported by the stub
        ap.set_offboard_setpoint(position, velocity,
                                 yaw if not mask & _IGNORE_YAW else _NAN,
                                 yaw_rate if not mask & _IGNORE_YAW_RATE else _NAN)
        self.stats.setpoints += 1

    def _on_timesync(self, link: _Link, frame: mavlink.Frame, address: tuple[str, int]) -> None:
        tc1, ts1 = mavlink.unpack_payload(frame)[:2]
        if tc1 == 0:   # a request: answer with our (simulated) clock in ns
            self._queue(link, d.MAVLink_timesync_message, dict(tc1=self.autopilot.time_us * 1000, ts1=ts1))
            self._flush(link, address)
