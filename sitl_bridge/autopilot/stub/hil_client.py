"""The autopilot side of PX4's simulator link, for the stub: what PX4's `simulator_mavlink` does.

TCP client to host:4560+i. On connect it sends one HEARTBEAT and one COMMAND_LONG
SET_MESSAGE_INTERVAL(HIL_STATE_QUATERNION), like PX4. Every HIL_SENSOR with id 0 becomes a
SensorFrame (units converted back: hPa, gauss, degE7, mm, cm/s) for `StubAutopilot.update`,
and is answered with exactly one HIL_ACTUATOR_CONTROLS carrying the same time_usec
(controls[0..3] = motors 1..4 in [0, 1], all 0 when disarmed; mode 1|128 when armed; flags 1 =
lockstep). HIL_GPS and HIL_STATE_QUATERNION that arrive with a HIL_SENSOR belong to its step.
The usual read of a sensor-estimating stub (one HIL_SENSOR [+ HIL_GPS], whole frames) skips
the frame objects: `hil_fused.FusedSensorStep`, the same components in two compiled calls
(the same answer, byte for byte); anything else takes the per-message path below.

Two ways to run it:
- in-process: `pump()` never blocks; the simulator's Lockstep calls it right after sending
  the sensor messages, in the same thread. It also pumps the MAVLink API when given one.
- as a process (`sitl-bridge stub -i N`): `run()` loops on select.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import math
import select
import socket
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from sitl_bridge import mavlink
from sitl_bridge.mavlink_kernels import FIELDS_BARO, FIELDS_MAG
from sitl_bridge.ports import HIL_BASE_PORT
from sitl_bridge.sensors import BaroSample, GpsSample, GroundTruth, SensorFrame

from .estimator import NO_TRUTH
from .hil_fused import FusedSensorStep, FusedStep
from .modes import system_id_for

if TYPE_CHECKING:
    from .autopilot import StubAutopilot
    from .mavlink_api import MavlinkApi

log = logging.getLogger(__name__)
d = mavlink.dialect

# PX4 asks for ground truth every 5 ms (for its logs); the ground-truth estimator wants it
# every step; the sensor-estimating stub logs nothing and asks for none (-1 = disabled),
# which saves encoding and decoding it on every step
PX4_STATE_INTERVAL_US = 5000
EVERY_STEP_INTERVAL_US = 1000
NO_STATE_INTERVAL_US = -1
_LOCKSTEP_FLAG = 1
_MODE_ARMED = d.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | d.MAV_MODE_FLAG_SAFETY_ARMED
_MODE_DISARMED = d.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
_EARTH_RADIUS_M = 6378137.0

_SENSOR = struct.Struct("<QfffffffffffffIB")
_GPS = struct.Struct("<QiiiHHHhhhHBBBH")
_STATE = struct.Struct("<Q4ffffiiihhhHHhhh")
_ACTUATOR_CLASS = d.MAVLink_hil_actuator_controls_message
_HIL_SENSOR = d.MAVLINK_MSG_ID_HIL_SENSOR
_HIL_GPS = d.MAVLINK_MSG_ID_HIL_GPS
_HIL_STATE_QUATERNION = d.MAVLINK_MSG_ID_HIL_STATE_QUATERNION
# HIL_ACTUATOR_CONTROLS payload with controls 5..16 always 0: the same bytes as the dialect's
# "<QQ16fB", with four arguments to pack instead of nineteen
_ACTUATORS = struct.Struct("<QQ4f48xB")
assert _ACTUATORS.size == _ACTUATOR_CLASS.unpacker.size


@dataclass
class HilClientStats:
    """Counters since construction (across reconnections)."""

    connections: int = 0
    sensor_msgs: int = 0
    gps_msgs: int = 0
    state_msgs: int = 0
    actuator_msgs: int = 0
    other_msgs: int = 0
    garbage_bytes: int = 0
    bad_crc: int = 0


class HilClient:
    """Connects a StubAutopilot to a simulator's HIL TCP server (see module docstring).

    instance: vehicle instance i (port base_port + i); defaults to the autopilot's.
    api: the vehicle's MavlinkApi, pumped by `pump()` after the HIL messages.
    state_interval_us: HIL_STATE_QUATERNION interval to ask for (SET_MESSAGE_INTERVAL param 2):
        default every step when the autopilot estimates from ground truth, else -1 (none);
        PX4_STATE_INTERVAL_US asks exactly what PX4 asks.
    """

    def __init__(self, autopilot: StubAutopilot, instance: int | None = None, host: str = "127.0.0.1",
                 base_port: int = HIL_BASE_PORT, *, api: MavlinkApi | None = None,
                 state_interval_us: int | None = None) -> None:
        self.autopilot = autopilot
        self.instance = autopilot.instance if instance is None else instance
        self.host = host
        self.port = base_port + self.instance
        self.api = api
        if state_interval_us is None:
            state_interval_us = EVERY_STEP_INTERVAL_US if autopilot.ground_truth_estimate else NO_STATE_INTERVAL_US
        self.state_interval_us = state_interval_us
        self._wants_truth = autopilot.ground_truth_estimate
        self.stats = HilClientStats()
        self._sock: socket.socket | None = None
        self._parser = mavlink.FrameParser()
        self._encoder = mavlink.FrameEncoder(system_id_for(self.instance), 1)
        self._truth: GroundTruth | None = None
        self._truth_origin: tuple[float, float, float] | None = None
        self.last_time_usec = 0
        # the usual step in two compiled calls (sensor-estimating autopilots; see hil_fused)
        self._fused = None if self._wants_truth else FusedSensorStep(
            autopilot, self._encoder.system_id, self._encoder.component_id)

    # --- connection ---------------------------------------------------------------------------
    @property
    def connected(self) -> bool:
        """True while the TCP connection to the simulator is up."""
        return self._sock is not None

    def fileno(self) -> int:
        """The TCP socket's descriptor, -1 when not connected."""
        return self._sock.fileno() if self._sock is not None else -1

    def try_connect(self) -> bool:
        """One connection attempt (PX4 retries forever; callers loop). True when connected."""
        if self._sock is not None:
            return True
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        try:
            sock.connect((self.host, self.port))
        except OSError as exc:
            sock.close()
            if exc.errno not in (errno.ECONNREFUSED, errno.ETIMEDOUT, errno.ECONNRESET, errno.EHOSTUNREACH):
                log.debug("vehicle %d: connect to %s:%d failed: %s", self.instance, self.host, self.port, exc)
            return False
        sock.setblocking(False)
        self._sock = sock
        self._parser = mavlink.FrameParser()
        self.stats.connections += 1
        log.info("vehicle %d: stub connected to simulator %s:%d", self.instance, self.host, self.port)
        self._send_hello()
        return True

    def connect(self, timeout_s: float, retry_s: float = 0.05) -> bool:
        """Retry `try_connect` until connected or `timeout_s` (wall) has passed."""
        deadline = time.monotonic() + timeout_s
        while not self.try_connect():
            if time.monotonic() >= deadline:
                return False
            time.sleep(retry_s)
        return True

    def close(self) -> None:
        """Close the simulator connection (the MAVLink API is closed by its owner)."""
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.close()
        self._sock = None

    def __enter__(self) -> HilClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _send_hello(self) -> None:
        heartbeat = self._encoder.pack(
            d.MAVLink_heartbeat_message, 0, d.MAV_TYPE_GENERIC, d.MAV_AUTOPILOT_PX4,
            _MODE_ARMED if self.autopilot.armed else _MODE_DISARMED, d.MAV_STATE_STANDBY, 3)
        interval = self._encoder.pack(
            d.MAVLink_command_long_message, float(d.MAVLINK_MSG_ID_HIL_STATE_QUATERNION),
            float(self.state_interval_us), 0.0, 0.0, 0.0, 0.0, 0.0, d.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 0, 0)
        self._send(interval + heartbeat)

    def _send(self, data: bytes) -> None:
        sock = self._sock
        if sock is None:
            return
        try:
            sent = sock.send(data)
        except BlockingIOError:
            sent = 0
        except OSError as exc:
            self._lost(f"send failed ({exc})")
            return
        while sent < len(data):
            # only when the simulator stops reading; bounded wait
            _, writable, _ = select.select([], [sock], [], 5.0)
            if not writable:
                self._lost("simulator stopped reading")
                return
            try:
                sent += sock.send(data[sent:])
            except BlockingIOError:
                continue
            except OSError as exc:
                self._lost(f"send failed ({exc})")
                return

    def _lost(self, why: str) -> None:
        log.warning("vehicle %d: simulator link lost: %s", self.instance, why)
        self.close()

    # --- lockstep -------------------------------------------------------------------------------
    def pump(self) -> int:
        """Handle whatever the simulator sent, answer each HIL_SENSOR, pump the API.

        Never blocks. Returns the number of HIL_SENSOR steps answered."""
        answered = 0
        sock = self._sock
        while sock is not None:
            try:
                data = sock.recv(65536)
            except (BlockingIOError, InterruptedError):
                break
            except OSError as exc:
                self._lost(f"receive failed ({exc})")
                break
            if not data:
                self._lost("connection closed by the simulator")
                break
            answered += self._handle_bytes(data)
            if len(data) < 65536:
                break
            sock = self._sock
        if self.api is not None:
            self.api.pump()
        return answered

    def _handle_bytes(self, data: bytes) -> int:
        parser = self._parser
        if self._fused is not None and not parser.holds_partial:
            fused = self._fused.handle(data, self._encoder.take_sequence)
            if fused is not None:
                self._count_fused(fused)
                self._send(fused.frame)
                self.stats.actuator_msgs += 1
                return 1
        parsed = parser.stats
        garbage, bad_crc = parsed.garbage_bytes, parsed.bad_crc
        frames = parser.feed(data)
        if parsed.garbage_bytes != garbage or parsed.bad_crc != bad_crc:  # rare: skip the sums otherwise
            self.stats.garbage_bytes += parsed.garbage_bytes - garbage
            self.stats.bad_crc += parsed.bad_crc - bad_crc
        pending: SensorFrame | None = None
        answered = 0
        for frame in frames:
            msgid = frame.msgid
            if msgid == _HIL_SENSOR:
                if pending is not None:
                    self._step(pending)
                    answered += 1
                pending = self._decode_sensor(frame.payload)
            elif msgid == _HIL_GPS:
                gps = self._decode_gps(frame.payload)
                self.stats.gps_msgs += 1
                if pending is not None and gps is not None:
                    pending.gps = gps
            elif msgid == _HIL_STATE_QUATERNION:
                self.stats.state_msgs += 1
                if self._wants_truth:   # only the ground-truth estimator reads it
                    self._truth = self._decode_state(frame.payload)
                    if pending is not None:
                        pending.truth = self._truth
            else:
                self.stats.other_msgs += 1
        if pending is not None:
            self._step(pending)
            answered += 1
        return answered

    def _count_fused(self, step: FusedStep) -> None:
        """The counters of a fused step, as the per-message path would have counted it."""
        self.last_time_usec = step.time_us
        self.stats.sensor_msgs += 1
        self._parser.stats.frames += step.frames_read
        if step.with_gps:
            self.stats.gps_msgs += 1

    def _step(self, frame: SensorFrame) -> None:
        command = self.autopilot.update(frame)
        if command.armed:
            c0, c1, c2, c3 = command.controls
            payload = _ACTUATORS.pack(frame.time_us, _LOCKSTEP_FLAG, c0, c1, c2, c3, _MODE_ARMED)
        else:
            payload = _ACTUATORS.pack(frame.time_us, _LOCKSTEP_FLAG, 0.0, 0.0, 0.0, 0.0, _MODE_DISARMED)
        self._send(self._encoder.frame(_ACTUATOR_CLASS.id, _ACTUATOR_CLASS.crc_extra, payload))
        self.stats.actuator_msgs += 1

    # --- decoding -------------------------------------------------------------------------------
    def _decode_sensor(self, payload: bytes) -> SensorFrame | None:
        (time_usec, ax, ay, az, gx, gy, gz, mx, my, mz, abs_pressure_hpa, _diff, pressure_alt_m,
         temperature_c, fields, sensor_id) = _SENSOR.unpack(payload)
        if sensor_id != 0:
            return None  # only the primary sensor drives the clock (PX4 lockstep)
        self.stats.sensor_msgs += 1
        self.last_time_usec = time_usec
        mag = (mx, my, mz) if fields & FIELDS_MAG == FIELDS_MAG else None
        baro = BaroSample(abs_pressure_hpa, temperature_c, pressure_alt_m) \
            if fields & FIELDS_BARO == FIELDS_BARO else None
        truth = self._truth if self._truth is not None else NO_TRUTH
        # plain tuples, not numpy arrays: this frame only feeds the stub's estimator, which
        # reads the values back as floats (an array costs more to build than to use here)
        return SensorFrame(time_usec, (ax, ay, az), (gx, gy, gz), mag, baro, None, truth)  # type: ignore[arg-type]

    def _decode_gps(self, payload: bytes) -> GpsSample | None:
        (_t, lat, lon, alt, eph, epv, vel, vn, ve, vd, cog, fix_type, satellites, gps_id, _yaw) = _GPS.unpack(payload)
        if gps_id != 0:
            return None
        return GpsSample(lat_e7=lat, lon_e7=lon, alt_mm=alt, eph_cm=eph, epv_cm=epv, vel_cm_s=vel, vn_cm_s=vn,
                         ve_cm_s=ve, vd_cm_s=vd, cog_cdeg=cog, fix_type=fix_type, satellites=satellites)

    def _decode_state(self, payload: bytes) -> GroundTruth:
        (_t, qw, qx, qy, qz, p, q, r, lat, lon, alt_mm, vx, vy, vz, _ias, _tas,
         xacc, yacc, zacc) = _STATE.unpack(payload)
        lat_deg, lon_deg, alt_m = lat * 1e-7, lon * 1e-7, alt_mm * 1e-3
        if self._truth_origin is None:
            self._truth_origin = (lat_deg, lon_deg, alt_m)
        lat0, lon0, alt0 = self._truth_origin
        north = math.radians(lat_deg - lat0) * _EARTH_RADIUS_M
        east = math.radians(lon_deg - lon0) * _EARTH_RADIUS_M * math.cos(math.radians(lat0))
        # plain tuples: GroundTruth keeps them as `raw` (Python floats, what the ground-truth
        # estimator reads) and builds the numpy views only if someone asks
        return GroundTruth(
            quaternion_ned_frd=(qw, qx, qy, qz),
            angular_velocity_frd_rad_s=(p, q, r),
            lat_e7=lat, lon_e7=lon, alt_mm=alt_mm,
            velocity_ned_m_s=(vx * 0.01, vy * 0.01, vz * 0.01),
            accel_ned_m_s2=(xacc * 1e-3, yacc * 1e-3, zacc * 1e-3),
            position_ned_m=(north, east, alt0 - alt_m),
        )

    # --- standalone process -------------------------------------------------------------------
    def run(self, should_stop: Callable[[], bool], *, retry_s: float = 0.5, poll_s: float = 0.1) -> None:
        """Blocking loop for a stub in its own process: connect (retrying like PX4), then answer
        the simulator and serve the API until `should_stop()` or the simulator hangs up."""
        api_fds = self.api.filenos() if self.api is not None else []
        while not should_stop():
            if self._sock is None:
                if self.stats.connections:
                    return  # the simulator hung up after a session: the caller decides what next
                if not self.try_connect():
                    if api_fds:
                        select.select(api_fds, [], [], retry_s)
                    else:
                        time.sleep(retry_s)
                    if self.api is not None:
                        self.api.pump()
                    continue
            select.select([self._sock, *api_fds], [], [], poll_s)
            self.pump()
