"""`HilLink`: the simulator side of PX4's simulator MAVLink protocol for one vehicle.

The simulator is the TCP server on host:4560+instance and the autopilot (PX4's
`simulator_mavlink`, the stub's HIL client, anything speaking the protocol) connects. Per
physics step the link sends exactly one HIL_SENSOR with id 0 (IMU every step; mag and baro
only when they updated, with their `fields_updated` bits), then HIL_GPS when a GPS sample is
due and HIL_STATE_QUATERNION ground truth at the requested interval, all in one TCP write.
It receives HIL_ACTUATOR_CONTROLS (controls[0..3] = motors 1..4, armed = mode & 128),
HEARTBEAT and COMMAND_LONG SET_MESSAGE_INTERVAL. Garbage bytes, split frames and bad
checksums are counted in `stats` and logged at debug level; they never break the link. The
usual read, one whole HIL_ACTUATOR_CONTROLS, is checked and decoded in one compiled call
(`mavlink_kernels.actuator_values`); anything else goes through the frame parser.

Simulated time goes on the wire as `time_usec = frame.time_us + offset`: the offset (one
step at first) keeps wire time strictly increasing when the simulation is reset in place,
because an autopilot's clock (PX4's lockstep clock) can never go back.
"""

from __future__ import annotations

import contextlib
import logging
import math
import select
import socket
import struct
import time
from typing import Any

import numpy as np

from sitl_bridge import mavlink
from sitl_bridge.hil.admission import Admission
from sitl_bridge.hil.errors import HilError, LinkClosed, LockstepTimeout
from sitl_bridge.hil.link_stats import AutopilotHeartbeat, LinkStats
from sitl_bridge.hil.sensor_frame import sensor_frame
from sitl_bridge.mavlink_kernels import SCRATCH_BYTES, actuator_values
from sitl_bridge.physics.simulation import MotorCommand
from sitl_bridge.physics.state import armed_command
from sitl_bridge.ports import HIL_BASE_PORT
from sitl_bridge.world.clock import DEFAULT_STEP_US

log = logging.getLogger(__name__)

DEFAULT_BASE_PORT = HIL_BASE_PORT

# SET_MESSAGE_INTERVAL param2 meanings (MAVLink common.xml).
INTERVAL_DISABLED = -1
INTERVAL_DEFAULT = 0

_INT16 = 32767
_UINT16 = 65535

_DISARMED = MotorCommand.disarmed()

_GPS_CLASS = mavlink.dialect.MAVLink_hil_gps_message
_STATE_CLASS = mavlink.dialect.MAVLink_hil_state_quaternion_message
_HIL_ACTUATOR_CONTROLS = mavlink.HIL_ACTUATOR_CONTROLS
_ACTUATOR_STRUCT = struct.Struct("<QQ16fB")  # time_usec, flags, controls[16], mode
_COMMAND_LONG_STRUCT = struct.Struct("<7fHBBB")  # param1..7, command, target sys/comp, confirmation


def _clamp_int(value: float, low: int, high: int) -> int:
    if value != value:
        return 0
    number = int(round(value))
    return low if number < low else high if number > high else number


def _i16(value: float) -> int:
    """Round into int16 (NaN -> 0)."""
    if value != value:
        return 0
    return -_INT16 if value < -_INT16 else _INT16 if value > _INT16 else int(round(value))


_MAX_INTERVAL_US = 2**31 - 1  # a longer interval asked for means "hardly ever"; keeps it a machine int


def _motor_value(value: float) -> float:
    return 0.0 if value != value or value < 0.0 else 1.0 if value > 1.0 else value


class HilLink:
    """Simulator-side TCP server of PX4's simulator protocol for vehicle `instance`.

    The server socket is bound in the constructor (so a port conflict fails at once); the
    autopilot connection is taken with `accept(timeout_s)`. A later `accept` after
    `disconnect()` takes a new autopilot (a restarted PX4).

    Args:
        instance: vehicle instance; the port is `base_port + instance`.
        host: address to listen on (127.0.0.1 by default, never all interfaces unless asked).
        base_port: 4560 like PX4's `px4-rc.simulator`.
        step_us: the physics step, used to keep wire time monotonic across resets.
        state_interval_us: HIL_STATE_QUATERNION interval before the autopilot asks for one
            (0: every step like Gazebo, -1: off). PX4 asks for 5000 us on connect.
        ground_truth: False: never send HIL_STATE_QUATERNION, whatever the autopilot asks (for
            one that provably does not read it: `AutopilotFleet.reads_hil_ground_truth`).
        system_id, component_id: ids of the simulator's messages (Gazebo's 1/200).
    """

    def __init__(
        self,
        instance: int,
        host: str = "127.0.0.1",
        base_port: int = DEFAULT_BASE_PORT,
        *,
        step_us: int = DEFAULT_STEP_US,
        state_interval_us: int = INTERVAL_DEFAULT,
        ground_truth: bool = True,
        system_id: int = 1,
        component_id: int = 200,
    ) -> None:
        self.instance = instance
        self.host = host
        self.port = base_port + instance
        self.step_us = step_us
        self.ground_truth = ground_truth
        self.default_state_interval_us = state_interval_us if ground_truth else INTERVAL_DISABLED
        self.stats = LinkStats()
        self.heartbeat: AutopilotHeartbeat | None = None
        self._encoder = mavlink.FrameEncoder(system_id, component_id)
        self._scratch = np.zeros(SCRATCH_BYTES, np.uint8)
        self._out = np.zeros(SCRATCH_BYTES, np.uint8)
        # load (or compile) the kernels now, not in a step
        actuator_values(b"", self._scratch)
        sensor_frame(self._out, self._scratch, 0, 1, 1, 0, *[0.0] * 6, False, 0.0, 0.0, 0.0, False, 0.0, 0.0, 0.0)
        self._server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self._server.bind((host, self.port))
        except OSError as exc:
            self._server.close()
            raise HilError(
                f"vehicle {instance}: cannot listen on {host}:{self.port} ({exc.strerror}); "
                "is another simulator using this instance? Pick free ones with --instance-base "
                "(sitl-bridge run) or -i (sitl-bridge stub)"
            ) from None
        self._server.listen(8)  # a stray peer in the backlog must not keep the autopilot out
        self._server.setblocking(False)
        self._admission = Admission(self._server, instance)
        self._client: socket.socket | None = None
        self._peer = ""
        self._time_offset_us = step_us  # first wire time is one step, never 0
        self._last_sent_wire_us = 0
        self._reset_connection_state()

    # -- connection ---------------------------------------------------------------------
    def _reset_connection_state(self) -> None:
        self._parser = mavlink.FrameParser()
        self._parser_garbage = 0
        self._parser_bad_crc = 0
        self.command: MotorCommand = _DISARMED
        self.actuators_flowing = False
        self._last_reply_wire_us = -1
        self.actuator_flags = 0
        self.state_interval_us = self.default_state_interval_us
        self._next_state_wire_us = 0
        self.heartbeat = None

    @property
    def connected(self) -> bool:
        """True while an autopilot is connected."""
        return self._client is not None

    @property
    def peer(self) -> str:
        """host:port of the connected autopilot ('' when none)."""
        return self._peer

    def fileno(self) -> int:
        """The connected socket's descriptor (for select/poll); -1 when not connected."""
        return self._client.fileno() if self._client is not None else -1

    def accept(self, timeout_s: float) -> bool:
        """Wait up to `timeout_s` for an autopilot. True once one is connected (at once if one
        already is). A peer counts only once it speaks as an autopilot (see `hil.admission`);
        what it sent until then is handled as the start of the connection."""
        if self._client is not None:
            return True
        admitted = self._admission.wait(timeout_s)
        if admitted is None:
            return False
        self._client = admitted.sock
        self._peer = admitted.peer
        self._reset_connection_state()
        self.stats.connections += 1
        self.stats.bytes_received += len(admitted.data)
        log.info("vehicle %d: autopilot connected from %s", self.instance, self._peer)
        self._handle_bytes(admitted.data)  # its greeting (HEARTBEAT, interval request)
        return True

    def disconnect(self) -> None:
        """Drop the autopilot connection (keeps listening for the next one)."""
        if self._client is not None:
            with contextlib.suppress(OSError):
                self._client.close()
            log.info("vehicle %d: autopilot connection closed", self.instance)
        self._client = None
        self._peer = ""
        self._reset_connection_state()

    def close(self) -> None:
        """Close the connection and the server socket (frees the port)."""
        self.disconnect()
        self._admission.close()
        with contextlib.suppress(OSError):
            self._server.close()

    def __enter__(self) -> HilLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- time -----------------------------------------------------------------------------
    def wire_time_us(self, time_us: int) -> int:
        """The `time_usec` that simulated time `time_us` has (or would have) on the wire."""
        return time_us + self._time_offset_us

    @property
    def last_sent_time_usec(self) -> int:
        """`time_usec` of the last HIL_SENSOR sent (0 before the first)."""
        return self._last_sent_wire_us

    # -- sending --------------------------------------------------------------------------
    def send_sensor_frame(self, frame: Any) -> None:
        """Send one step's messages: exactly one HIL_SENSOR (id 0), then HIL_GPS when the
        frame has a GPS sample, then HIL_STATE_QUATERNION when due. One TCP write."""
        ax, ay, az = frame.accel_frd_m_s2.tolist()
        gx, gy, gz = frame.gyro_frd_rad_s.tolist()
        mag = frame.mag_frd_gauss
        self.send_sensor_values(frame.time_us, (ax, ay, az, gx, gy, gz, None if mag is None else tuple(mag.tolist()),
                                                frame.baro, frame.gps), frame.truth)

    def state_due(self, time_us: int) -> bool:
        """Whether the step at simulated `time_us` carries HIL_STATE_QUATERNION (then
        `send_sensor_values` needs its ground truth)."""
        return self.state_interval_us >= 0 and self._wire_us(time_us) >= self._next_state_wire_us

    def _wire_us(self, time_us: int) -> int:
        """The autopilot-clock time the step at simulated `time_us` goes out at: after a
        simulation reset in place the autopilot's clock continues instead of going back."""
        wire_us = time_us + self._time_offset_us
        return wire_us if wire_us > self._last_sent_wire_us else self._last_sent_wire_us + self.step_us

    def send_sensor_values(self, time_us: int, values: tuple, truth: Any = None) -> None:
        """`send_sensor_frame` from the values of `SensorSuite.sample_values` (accel and gyro
        FRD, mag FRD or None, baro, GPS) without building a frame; `truth` (a `GroundTruth`)
        is needed only when `state_due(time_us)`."""
        client = self._client
        if client is None:
            raise LinkClosed(f"vehicle {self.instance}: no autopilot connected", instance=self.instance)
        wire_us = self._wire_us(time_us)
        self._time_offset_us = wire_us - time_us  # changes only after a reset in place
        data = self._encode_sensor(values, wire_us)
        gps = values[8]
        if gps is not None:
            data += self._encode_gps(gps, wire_us)
            self.stats.gps_msgs += 1
        if self.state_interval_us >= 0 and wire_us >= self._next_state_wire_us:
            if truth is None:
                raise ValueError(f"vehicle {self.instance}: HIL_STATE_QUATERNION due without a ground truth")
            data += self._encode_state(truth, wire_us)
            self.stats.state_msgs += 1
            interval = self.state_interval_us
            # Schedule on a fixed grid so e.g. 5000 us over 4000 us steps averages 200 Hz.
            if interval <= 0 or self._next_state_wire_us == 0:
                self._next_state_wire_us = wire_us + interval
            else:
                self._next_state_wire_us += interval
                if self._next_state_wire_us <= wire_us:
                    self._next_state_wire_us = wire_us + interval
        self._send(data)
        self._last_sent_wire_us = wire_us
        self.stats.sensor_msgs += 1

    def _encode_sensor(self, values: tuple, wire_us: int) -> bytes:
        ax, ay, az, gx, gy, gz, mag, baro, _ = values
        encoder = self._encoder
        sequence = encoder.take_sequence()
        mx, my, mz = (0.0, 0.0, 0.0) if mag is None else mag
        hpa, celsius, alt_m = (0.0, 0.0, 0.0) if baro is None else (
            float(baro.pressure_hpa), float(baro.temperature_c), float(baro.pressure_alt_m))
        size = sensor_frame(self._out, self._scratch, sequence, encoder.system_id, encoder.component_id, wire_us,
                            ax, ay, az, gx, gy, gz, mag is not None, mx, my, mz,
                            baro is not None, hpa, celsius, alt_m)
        return self._out[:size].tobytes()

    def _encode_gps(self, gps: Any, wire_us: int) -> bytes:
        return self._encoder.pack(
            _GPS_CLASS,
            wire_us,
            _clamp_int(gps.lat_e7, -900_000_000, 900_000_000),
            _clamp_int(gps.lon_e7, -1_800_000_000, 1_800_000_000),
            _clamp_int(gps.alt_mm, -(2**31), 2**31 - 1),
            _clamp_int(gps.eph_cm, 0, _UINT16),
            _clamp_int(gps.epv_cm, 0, _UINT16),
            _clamp_int(gps.vel_cm_s, 0, _UINT16),
            _clamp_int(gps.vn_cm_s, -_INT16, _INT16),
            _clamp_int(gps.ve_cm_s, -_INT16, _INT16),
            _clamp_int(gps.vd_cm_s, -_INT16, _INT16),
            _clamp_int(gps.cog_cdeg, 0, _UINT16),
            _clamp_int(gps.fix_type, 0, 255),
            _clamp_int(gps.satellites, 0, 255),
            0,  # id: GPS instance 0
            0,  # yaw: 0 = not available
        )

    def _encode_state(self, truth: Any, wire_us: int) -> bytes:
        # `raw`: the same values as plain floats (no arrays built on the way, ~every step for PX4)
        (qw, qx, qy, qz), (p, q, r), (vn, ve, vd), (an, ae, ad), _ = truth.raw
        speed_cm_s = min(int(math.sqrt(vn * vn + ve * ve + vd * vd) * 100.0), _UINT16)
        return self._encoder.pack(
            _STATE_CLASS,
            wire_us,
            qw, qx, qy, qz,
            p, q, r,
            # geodetic values come from the sensor suite as valid integers already
            int(truth.lat_e7), int(truth.lon_e7), int(truth.alt_mm),
            _i16(vn * 100.0), _i16(ve * 100.0), _i16(vd * 100.0),
            speed_cm_s, speed_cm_s,
            # Gazebo sends NED m/s^2 x 1000 and PX4 divides by 1000 (fact sheet A2).
            _i16(an * 1000.0), _i16(ae * 1000.0), _i16(ad * 1000.0),
        )

    def _send(self, data: bytes, timeout_s: float = 5.0) -> None:
        client = self._client
        assert client is not None
        view = memoryview(data)
        try:
            sent = client.send(view)
        except BlockingIOError:
            sent = 0
        except OSError as exc:
            self._lost(f"send failed ({exc})")
        while sent < len(view):
            # Only when the autopilot stops reading: wait, bounded, for buffer space.
            _, writable, _ = select.select([], [client], [], timeout_s)
            if not writable:
                raise LinkClosed(
                    f"vehicle {self.instance}: autopilot stopped reading for {timeout_s} s",
                    instance=self.instance,
                )
            try:
                sent += client.send(view[sent:])
            except BlockingIOError:
                continue
            except OSError as exc:
                self._lost(f"send failed ({exc})")
        self.stats.bytes_sent += len(data)

    def _lost(self, why: str) -> None:
        instance = self.instance
        self.disconnect()
        raise LinkClosed(f"vehicle {instance}: autopilot link lost: {why}", instance=instance)

    # -- receiving ------------------------------------------------------------------------
    def poll(self) -> int:
        """Read and handle whatever the autopilot sent, without blocking. Returns the number
        of HIL_ACTUATOR_CONTROLS handled. Raises LinkClosed when the autopilot hung up."""
        client = self._client
        if client is None:
            return 0
        handled = 0
        while True:
            try:
                data = client.recv(65536)
            except (BlockingIOError, InterruptedError):
                return handled
            except OSError as exc:
                self._lost(f"receive failed ({exc})")
            if not data:
                self._lost("connection closed by the autopilot")
            self.stats.bytes_received += len(data)
            handled += self._handle_bytes(data)
            if len(data) < 65536:
                return handled

    def _handle_bytes(self, data: bytes) -> int:
        parser = self._parser
        if not parser.holds_partial:  # the usual read, one whole answer: compiled check and decode
            ok, time_usec, flags, mode, u1, u2, u3, u4 = actuator_values(data, self._scratch)
            if ok:
                parser.stats.frames += 1
                self._actuators(time_usec, flags, mode, u1, u2, u3, u4)
                return 1
        handled = 0
        for frame in parser.feed(data):
            msgid = frame.msgid
            if msgid == _HIL_ACTUATOR_CONTROLS:
                self._handle_actuators(frame.payload)
                handled += 1
            elif msgid == mavlink.HEARTBEAT:
                self._handle_heartbeat(frame)
            elif msgid == mavlink.COMMAND_LONG:
                self._handle_command(frame)
            else:
                self.stats.other_msgs += 1
                log.debug("vehicle %d: ignoring message id %d", self.instance, frame.msgid)
        stats = parser.stats
        if stats.garbage_bytes != self._parser_garbage or stats.bad_crc != self._parser_bad_crc:
            self.stats.garbage_bytes += stats.garbage_bytes - self._parser_garbage
            self.stats.bad_crc += stats.bad_crc - self._parser_bad_crc
            self._parser_garbage, self._parser_bad_crc = stats.garbage_bytes, stats.bad_crc
            log.debug(
                "vehicle %d: skipped bytes on the simulator link (garbage %d, bad CRC %d so far)",
                self.instance, self.stats.garbage_bytes, self.stats.bad_crc,
            )
        return handled

    def _handle_actuators(self, payload: bytes) -> None:
        values = _ACTUATOR_STRUCT.unpack(payload)
        self._actuators(values[0], values[1], values[18], *values[2:6])

    def _actuators(self, time_usec: int, flags: int, mode: int, u1: float, u2: float, u3: float, u4: float) -> None:
        self.stats.actuator_msgs += 1
        self.actuators_flowing = True
        self.actuator_flags = flags
        if time_usec < self._last_sent_wire_us:
            self.stats.stale_actuator_msgs += 1
            if time_usec < self._last_reply_wire_us:
                return  # older than what we already applied: out of order, drop
        # an answer stamped after the last step sent answers that step, not later ones (a bogus
        # time must not make every later step look answered and the lockstep run free)
        self._last_reply_wire_us = max(self._last_reply_wire_us, min(time_usec, self._last_sent_wire_us))
        if mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED:
            if not (0.0 <= u1 <= 1.0 and 0.0 <= u2 <= 1.0 and 0.0 <= u3 <= 1.0 and 0.0 <= u4 <= 1.0):
                # out of range or NaN (rare): limit each
                u1, u2, u3, u4 = _motor_value(u1), _motor_value(u2), _motor_value(u3), _motor_value(u4)
            self.command = armed_command((u1, u2, u3, u4))
        else:
            self.command = _DISARMED

    def _handle_heartbeat(self, frame: mavlink.Frame) -> None:
        _custom_mode, _type, autopilot, base_mode, _status, _version = mavlink.unpack_payload(frame)
        self.stats.heartbeats += 1
        self.heartbeat = AutopilotHeartbeat(frame.system_id, frame.component_id, autopilot, base_mode)

    def _handle_command(self, frame: mavlink.Frame) -> None:
        p1, p2, _p3, _p4, _p5, _p6, _p7, command, _ts, _tc, _conf = _COMMAND_LONG_STRUCT.unpack(
            frame.payload
        )
        self.stats.commands += 1
        if command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL and p1 == mavlink.HIL_STATE_QUATERNION \
                and self.ground_truth:
            if not math.isfinite(p2):
                log.debug("vehicle %d: ignoring a HIL_STATE_QUATERNION interval of %s", self.instance, p2)
                return
            interval = int(max(-1.0, min(p2, _MAX_INTERVAL_US)))
            if interval == INTERVAL_DEFAULT:
                interval = self.default_state_interval_us
            self.state_interval_us = interval if interval > 0 else (
                INTERVAL_DISABLED if interval < 0 else 0
            )
            self._next_state_wire_us = 0
            log.debug("vehicle %d: HIL_STATE_QUATERNION interval %d us", self.instance, interval)
        else:
            log.debug("vehicle %d: ignoring command %d", self.instance, command)

    # -- lockstep ---------------------------------------------------------------------------
    def answered(self, time_us: int | None = None) -> bool:
        """True when the autopilot answered the step at simulated `time_us` (default: the last
        step sent), or when no actuator message has arrived yet on this connection (before
        that, steps do not wait: PX4 is still booting)."""
        if not self.actuators_flowing:
            return True
        wire = self._last_sent_wire_us if time_us is None else time_us + self._time_offset_us
        return self._last_reply_wire_us >= wire

    def receive_actuators(self, time_us: int, timeout_s: float) -> MotorCommand:
        """The command answering the step at simulated `time_us`, waiting up to `timeout_s`
        (wall) for it once actuators flow. Raises LockstepTimeout (and counts it)."""
        self.poll()
        if self.answered(time_us):
            return self.command
        end = time.monotonic() + timeout_s  # a timeout only: the link never paces
        while True:
            remaining = end - time.monotonic()
            if remaining <= 0:
                self.stats.timeouts += 1
                raise LockstepTimeout(
                    f"vehicle {self.instance}: no HIL_ACTUATOR_CONTROLS for time_usec "
                    f"{self.wire_time_us(time_us)} within {timeout_s} s",
                    instances=(self.instance,), time_us=time_us,
                )
            select.select([self._client], [], [], remaining)
            self.poll()
            if self.answered(time_us):
                return self.command
