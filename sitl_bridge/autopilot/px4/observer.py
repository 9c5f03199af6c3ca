"""Watching a PX4 over its GCS MAVLink port (UDP 18570+N), the way QGroundControl does:
heartbeats out so PX4 streams to us; HEARTBEAT, SYS_STATUS, HOME_POSITION, LOCAL_POSITION_NED,
EXTENDED_SYS_STATE, COMMAND_ACK and PARAM_VALUE in. Parameters that must hold a value are read back and set again
(PARAM_SET, PX4's bytewise int encoding) when they differ."""

from __future__ import annotations

import contextlib
import logging
import socket
import struct
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from sitl_bridge import mavlink
from sitl_bridge.autopilot.fleet import VehicleSummary
from sitl_bridge.autopilot.modes import mode_name
from sitl_bridge.ports import GCS_BIND_BASE_PORT

log = logging.getLogger(__name__)

GCS_BASE_PORT = GCS_BIND_BASE_PORT
MAV_SYS_STATUS_PREARM_CHECK = 0x10000000


@dataclass
class Px4Observation:
    """What PX4 told us on its GCS MAVLink port (and console) since the last start."""

    heartbeat: bool = False
    armed: bool = False
    custom_mode: int = 0
    system_status: int = 0  # HEARTBEAT.system_status: MAV_STATE (PX4: CRITICAL in a failsafe)
    landed_state: int = 0  # EXTENDED_SYS_STATE.landed_state: MAV_LANDED_STATE (0: not reported yet)
    prearm_ok: bool = False
    home_ok: bool = False
    ready_for_takeoff_line: bool = False
    params_pending: tuple[str, ...] = ()  # `wall` parameters not yet confirmed
    position_ned_m: tuple[float, float, float] | None = None  # PX4's estimate (LOCAL_POSITION_NED)
    velocity_ned_m_s: tuple[float, float, float] | None = None
    attitude_rad: tuple[float, float, float] | None = None  # PX4's estimate (ATTITUDE): roll, pitch, yaw
    acks: dict[int, int] = field(default_factory=dict)  # command -> MAV_RESULT
    received_wall_s: dict[str, float] = field(default_factory=dict)
    """Message name -> time.monotonic() when it last arrived (how old each report is)."""

    def summary(self) -> VehicleSummary:
        """Mode name and armed flag of PX4's last HEARTBEAT."""
        return VehicleSummary(mode_name(self.custom_mode), self.armed)

    @property
    def ready(self) -> bool:
        """Heartbeat seen, pre-arm checks passing (estimator healthy), home position set, the
        `wall` timeouts confirmed."""
        return (
            self.heartbeat and self.home_ok and not self.params_pending
            and (self.prearm_ok or self.ready_for_takeoff_line)
        )


_REPORTS = {msgid: name for name, msgid in (
    ("HEARTBEAT", mavlink.HEARTBEAT),
    ("EXTENDED_SYS_STATE", mavlink.dialect.MAVLINK_MSG_ID_EXTENDED_SYS_STATE),
    ("LOCAL_POSITION_NED", mavlink.dialect.MAVLINK_MSG_ID_LOCAL_POSITION_NED),
    ("ATTITUDE", mavlink.dialect.MAVLINK_MSG_ID_ATTITUDE),
)}  # the reports an in-air refusal rests on (`Px4Observation.received_wall_s`)

_PARAM_FLOAT = struct.Struct("<f")
_PARAM_INT = struct.Struct("<i")


class GcsObserver:
    """A UDP socket talking to PX4's GCS link port: heartbeats out (so PX4 streams to us),
    HEARTBEAT / SYS_STATUS / HOME_POSITION in; reads back parameters that must hold a value
    and sets them (PARAM_SET, PX4's bytewise int encoding) when they differ."""

    RESEND_S = 0.1
    """Wall seconds between heartbeats and parameter requests. PX4 streams to this port only
    after a heartbeat, and each parameter check is a request and a reply, so a PX4 (re)start
    waits for these sends: every 0.5 s a restart took 1.7-1.8 s, every 0.1 s 1.3-1.4 s."""

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
                name = _REPORTS.get(msgid)
                if name is not None:
                    obs.received_wall_s[name] = now
                if msgid == mavlink.HEARTBEAT:
                    msg = mavlink.decode_frame(self._codec, frame)
                    obs.heartbeat = True
                    obs.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                    obs.custom_mode = msg.custom_mode
                    obs.system_status = msg.system_status
                elif msgid == mavlink.dialect.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
                    _vtol_state, obs.landed_state = mavlink.unpack_payload(frame)
                elif msgid == mavlink.dialect.MAVLINK_MSG_ID_SYS_STATUS:
                    msg = mavlink.decode_frame(self._codec, frame)
                    obs.prearm_ok = bool(msg.onboard_control_sensors_health & MAV_SYS_STATUS_PREARM_CHECK)
                elif msgid == mavlink.dialect.MAVLINK_MSG_ID_HOME_POSITION:
                    obs.home_ok = True
                elif msgid == mavlink.dialect.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
                    _t, x, y, z, vx, vy, vz = mavlink.unpack_payload(frame)
                    obs.position_ned_m = (x, y, z)
                    obs.velocity_ned_m_s = (vx, vy, vz)
                elif msgid == mavlink.dialect.MAVLINK_MSG_ID_ATTITUDE:
                    _t, roll, pitch, yaw, *_rates = mavlink.unpack_payload(frame)
                    obs.attitude_rad = (roll, pitch, yaw)
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
