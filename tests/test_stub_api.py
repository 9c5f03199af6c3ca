"""The stub's MAVLink API over real UDP sockets, against a pymavlink peer written here."""

from __future__ import annotations

import math
import socket
import struct
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from sitl_bridge import mavlink
from sitl_bridge.autopilot.stub import MavlinkApi
from sitl_bridge.autopilot.stub.harness import StubHarness
from sitl_bridge.autopilot.stub.mavlink_api import (
    API_BIND_BASE_PORT,
    API_REMOTE_BASE_PORT,
    BATCH_MAX_MESSAGES,
)
from sitl_bridge.world.loader import load_world

d = mavlink.dialect
WORLD = load_world(Path(__file__).resolve().parents[1] / "worlds" / "empty.yaml")
HOLD_CUSTOM_MODE = 50593792
OFFBOARD_CUSTOM_MODE = 393216
PEER_SYSID, PEER_COMPID = 245, 190   # MAVSDK's ids


class Peer:
    """A MAVSDK-like ground station: listens on 14540+i, talks to the vehicle that writes to it."""

    def __init__(self, instance: int, pump: Callable[[], None]) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", API_REMOTE_BASE_PORT + instance))
        self.sock.settimeout(0.002)
        self.vehicle = ("127.0.0.1", API_BIND_BASE_PORT + instance)
        self.codec = mavlink.new_codec(PEER_SYSID, PEER_COMPID)
        self.pump = pump
        self.backlog: list = []   # messages read while the test was not looking for any
        self._pending: list = []

    def send(self, message) -> None:
        self.sock.sendto(message.pack(self.codec), self.vehicle)

    def send_raw(self, data: bytes) -> None:
        self.sock.sendto(data, self.vehicle)

    def receive(self, wanted: Callable[[object], bool], timeout_s: float = 3.0):
        """First message for which wanted(msg) holds; pumps the vehicle while waiting (wall).
        Messages before it are dropped; those after it (same datagram) wait for the next call."""
        deadline = time.monotonic() + timeout_s
        while True:
            while self._pending:
                msg = self._pending.pop(0)
                if wanted(msg):
                    return msg
            if time.monotonic() > deadline:
                raise AssertionError("expected message not received")
            self.pump()
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                continue
            self._pending += [mavlink.decode_frame(self.codec, f) for f in mavlink.FrameParser().feed(data)]

    def receive_frame(self, msgid: int, timeout_s: float = 3.0) -> mavlink.Frame:
        """The next raw frame with `msgid` (bytes as sent, nothing decoded)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.pump()
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                continue
            for frame in mavlink.FrameParser().feed(data):
                if frame.msgid == msgid:
                    return frame
        raise AssertionError(f"no message {msgid} received")

    def drain(self) -> list:
        """Every message waiting in the socket now."""
        parser = mavlink.FrameParser()
        messages, self._pending = self._pending, []
        while True:
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                return messages
            messages += [mavlink.decode_frame(self.codec, f) for f in parser.feed(data)]

    def close(self) -> None:
        self.sock.close()


def of_type(name: str) -> Callable[[object], bool]:
    return lambda msg: msg.get_type() == name


@pytest.fixture
def vehicle(free_instance: int):
    """(harness, api, peer, advance(seconds)) for a ground-truth stub that is ready to arm."""
    harness = StubHarness(WORLD, seed=11, ground_truth_estimate=True)
    api = MavlinkApi(harness.autopilot, free_instance, gcs=False)
    peer = Peer(free_instance, api.pump)

    def advance(seconds: float) -> None:
        """Step the simulation; the peer reads as it goes (a full UDP buffer drops datagrams)."""
        for k in range(round(seconds / 0.004)):
            harness.run_for(0.004)
            api.pump()
            if k % 25 == 24:
                peer.backlog += peer.drain()

    advance(0.2)
    try:
        yield harness, api, peer, advance
    finally:
        peer.close()
        api.close()
        harness.close()


def command_long(command: int, *params: float, target: int = 0):
    p = list(params) + [float("nan")] * (7 - len(params))
    return d.MAVLink_command_long_message(target, 1, command, 0, *p)


def test_heartbeat_says_px4_quadrotor_in_hold(vehicle) -> None:
    _, api, peer, advance = vehicle
    advance(1.1)
    hb = peer.receive(of_type("HEARTBEAT"))
    assert hb.get_srcSystem() == api.system_id and hb.get_srcComponent() == 1
    assert hb.type == d.MAV_TYPE_QUADROTOR and hb.autopilot == d.MAV_AUTOPILOT_PX4
    assert hb.base_mode & d.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert not hb.base_mode & d.MAV_MODE_FLAG_SAFETY_ARMED
    assert hb.custom_mode == HOLD_CUSTOM_MODE
    assert hb.system_status == d.MAV_STATE_STANDBY and hb.mavlink_version == 3


def test_streams_carry_what_mavsdk_health_needs(vehicle) -> None:
    _, api, peer, advance = vehicle
    advance(2.1)
    messages = peer.backlog + peer.drain()
    latest = {m.get_type(): m for m in messages}
    status = latest["SYS_STATUS"]
    ready = 0x1000002F   # gyro, accel, mag, baro, GPS, prearm
    assert status.onboard_control_sensors_present & ready == ready
    assert status.onboard_control_sensors_health & ready == ready
    assert latest["HOME_POSITION"].latitude == pytest.approx(473977420, abs=200)
    assert latest["EXTENDED_SYS_STATE"].landed_state == d.MAV_LANDED_STATE_ON_GROUND
    assert latest["GPS_RAW_INT"].fix_type >= 3 and latest["GPS_RAW_INT"].satellites_visible >= 6
    assert latest["LOCAL_POSITION_NED"].z == pytest.approx(0.0, abs=0.05)
    counts = {name: sum(m.get_type() == name for m in messages) for name in latest}
    # PX4-like rates in simulated time (2.3 s with the fixture's 0.2 s): 1 Hz heartbeat,
    # 50 Hz attitude, 30 Hz local position
    assert 2 <= counts["HEARTBEAT"] <= 4
    assert 108 <= counts["ATTITUDE"] <= 118
    assert 64 <= counts["LOCAL_POSITION_NED"] <= 72
    for name in ("ATTITUDE_QUATERNION", "GLOBAL_POSITION_INT", "BATTERY_STATUS"):
        assert counts[name] >= 1


def test_client_streams_carry_only_what_sitl_bridge_client_reads(free_instance: int) -> None:
    """api_streams="client" (the Gymnasium env's `api_telemetry="client"`): PX4's client set and
    rates (px4_params/px4-rc.mavlink), no attitude or battery streams."""
    harness = StubHarness(WORLD, seed=11, ground_truth_estimate=True)
    api = MavlinkApi(harness.autopilot, free_instance, gcs=False, api_streams="client")
    peer = Peer(free_instance, api.pump)
    try:
        messages = []
        for k in range(round(2.0 / 0.004)):
            harness.run_for(0.004)
            api.pump()
            if k % 25 == 24:
                messages += peer.drain()
        messages += peer.drain()
        counts: dict[str, int] = {}
        for m in messages:
            counts[m.get_type()] = counts.get(m.get_type(), 0) + 1
        assert set(counts) == {"HEARTBEAT", "SYS_STATUS", "EXTENDED_SYS_STATE", "LOCAL_POSITION_NED",
                               "GLOBAL_POSITION_INT", "GPS_RAW_INT", "HOME_POSITION"}
        assert 95 <= counts["GLOBAL_POSITION_INT"] <= 101   # 50 Hz over 2 s of simulated time
        assert 18 <= counts["GPS_RAW_INT"] <= 21 and 9 <= counts["SYS_STATUS"] <= 11
        with pytest.raises(ValueError, match="api_streams"):
            MavlinkApi(harness.autopilot, free_instance, gcs=False, api_streams="everything")
    finally:
        peer.close()
        api.close()
        harness.close()


def test_arm_is_acknowledged_by_compid_1_and_shows_in_heartbeat(vehicle) -> None:
    _, api, peer, advance = vehicle
    peer.send(command_long(d.MAV_CMD_COMPONENT_ARM_DISARM, 1.0, target=api.system_id))
    ack = peer.receive(of_type("COMMAND_ACK"))
    assert ack.command == d.MAV_CMD_COMPONENT_ARM_DISARM and ack.result == d.MAV_RESULT_ACCEPTED
    assert (ack.get_srcSystem(), ack.get_srcComponent()) == (api.system_id, 1)
    assert (ack.target_system, ack.target_component) == (PEER_SYSID, PEER_COMPID)
    hb = peer.receive(of_type("HEARTBEAT"))
    assert hb.base_mode & d.MAV_MODE_FLAG_SAFETY_ARMED and hb.system_status == d.MAV_STATE_ACTIVE


def test_unknown_command_is_unsupported_and_foreign_commands_are_ignored(vehicle) -> None:
    _, api, peer, _ = vehicle
    peer.send(command_long(31010, 1.0, target=api.system_id + 1))   # another vehicle's
    peer.send(command_long(31010, 1.0, target=api.system_id))
    ack = peer.receive(of_type("COMMAND_ACK"))
    assert ack.command == 31010 and ack.result == d.MAV_RESULT_UNSUPPORTED
    peer.send(d.MAVLink_command_int_message(api.system_id, 1, 0, 31011, 0, 0, 0, 0, 0, 0, 0, 0, 0))
    ack = peer.receive(of_type("COMMAND_ACK"))
    assert ack.command == 31011 and ack.result == d.MAV_RESULT_UNSUPPORTED
    assert api.stats.commands == 2 and api.stats.unsupported_commands == 2


def test_takeoff_then_offboard_velocity_from_set_position_target(vehicle) -> None:
    harness, api, peer, advance = vehicle
    ap = harness.autopilot
    for command in (command_long(d.MAV_CMD_COMPONENT_ARM_DISARM, 1.0), command_long(d.MAV_CMD_NAV_TAKEOFF)):
        peer.send(command)
        assert peer.receive(of_type("COMMAND_ACK")).result == d.MAV_RESULT_ACCEPTED
    advance(5.0)
    # MAVSDK's set_velocity_ned: LOCAL_NED, type_mask 0x09C7, yaw in rad
    setpoint = d.MAVLink_set_position_target_local_ned_message(
        0, api.system_id, 1, d.MAV_FRAME_LOCAL_NED, 0x09C7, 0, 0, 0, 1.0, 0.0, -0.5, 0, 0, 0, 0.0, 0.0)
    peer.send(setpoint)
    peer.send(command_long(d.MAV_CMD_DO_SET_MODE, 1 | 128, 6, 0))
    ack = peer.receive(lambda m: m.get_type() == "COMMAND_ACK" and m.command == d.MAV_CMD_DO_SET_MODE)
    assert ack.result == d.MAV_RESULT_ACCEPTED
    assert ap.commander.offboard.velocity_ned_m_s == (1.0, 0.0, -0.5)
    assert ap.commander.offboard.position_ned_m[0] != ap.commander.offboard.position_ned_m[0]  # NaN
    hb = peer.receive(of_type("HEARTBEAT"))
    assert hb.custom_mode == OFFBOARD_CUSTOM_MODE
    start = harness.position_ned_m.copy()
    for _ in range(20):   # 20 Hz stream for 1 s
        peer.send(setpoint)
        advance(0.05)
    assert harness.position_ned_m[0] - start[0] > 0.25
    assert api.stats.setpoints == 21


def _int32_bytes(value: int) -> float:
    return struct.unpack("<f", struct.pack("<i", value))[0]


def _int32_value(wire: float) -> int:
    return struct.unpack("<i", struct.pack("<f", wire))[0]


def test_param_read_and_set_round_trip_with_bytewise_int32(vehicle) -> None:
    harness, api, peer, _ = vehicle
    table = harness.autopilot.params
    peer.send(d.MAVLink_param_request_read_message(api.system_id, 1, b"CAL_ACC0_ID", -1))
    value = peer.receive(of_type("PARAM_VALUE"))
    assert value.param_id == "CAL_ACC0_ID" and value.param_type == d.MAV_PARAM_TYPE_INT32
    assert _int32_value(value.param_value) == int(table["CAL_ACC0_ID"]) != 0
    assert value.param_count == len(table) and value.param_index == table.index_of("CAL_ACC0_ID")

    peer.send(d.MAVLink_param_set_message(api.system_id, 1, b"COM_OBL_RC_ACT", _int32_bytes(4),
                                          d.MAV_PARAM_TYPE_INT32))
    echo = peer.receive(lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == "COM_OBL_RC_ACT")
    assert echo.param_type == d.MAV_PARAM_TYPE_INT32 and _int32_value(echo.param_value) == 4
    assert table["COM_OBL_RC_ACT"] == 4

    # an INT32 whose bits are a signalling NaN survives unchanged (raw frames both ways)
    tricky = -4194305
    payload = struct.pack("<iBB16sB", tricky, api.system_id, 1, b"COM_OBL_RC_ACT", d.MAV_PARAM_TYPE_INT32)
    peer.send_raw(mavlink.FrameEncoder(PEER_SYSID, PEER_COMPID).frame(
        d.MAVLINK_MSG_ID_PARAM_SET, d.MAVLink_param_set_message.crc_extra, payload))
    frame = peer.receive_frame(d.MAVLINK_MSG_ID_PARAM_VALUE)
    assert frame.payload[:4] == struct.pack("<i", tricky) and table["COM_OBL_RC_ACT"] == tricky

    peer.send(d.MAVLink_param_set_message(api.system_id, 1, b"MIS_TAKEOFF_ALT", 3.5, d.MAV_PARAM_TYPE_REAL32))
    echo = peer.receive(lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == "MIS_TAKEOFF_ALT")
    assert echo.param_type == d.MAV_PARAM_TYPE_REAL32 and echo.param_value == pytest.approx(3.5)
    assert table["MIS_TAKEOFF_ALT"] == pytest.approx(3.5)


def test_param_list_streams_every_parameter(vehicle) -> None:
    harness, api, peer, _ = vehicle
    table = harness.autopilot.params
    peer.send(d.MAVLink_param_request_list_message(api.system_id, 1))
    seen: set[int] = set()
    while len(seen) < len(table):
        value = peer.receive(of_type("PARAM_VALUE"))
        assert value.param_count == len(table)
        seen.add(value.param_index)
    assert seen == set(range(len(table)))
    assert {"MPC_XY_VEL_MAX", "COM_OF_LOSS_T", "SYS_HITL", "SDLOG_MODE"} <= {p.name for p in table}


def test_garbage_datagrams_are_counted_and_ignored(vehicle) -> None:
    _, api, peer, _ = vehicle
    good = command_long(d.MAV_CMD_REQUEST_MESSAGE, float(d.MAVLINK_MSG_ID_AUTOPILOT_VERSION)).pack(peer.codec)
    bad_crc = bytearray(good)
    bad_crc[-1] ^= 0xFF
    for junk in (b"", b"\x00" * 300, bytes(range(256)), good[:7], bytes(bad_crc), b"\xfd" * 40):
        peer.send_raw(junk)
    peer.send_raw(good)
    version = peer.receive(of_type("AUTOPILOT_VERSION"))
    assert version.capabilities & d.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    assert version.capabilities & d.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    assert api.stats.garbage_datagrams >= 5
    assert api.stats.bad_crc >= 1


def test_request_message_and_message_interval(vehicle) -> None:
    _, api, peer, advance = vehicle
    peer.send(command_long(d.MAV_CMD_REQUEST_MESSAGE, float(d.MAVLINK_MSG_ID_HOME_POSITION)))
    assert peer.receive(of_type("COMMAND_ACK")).result == d.MAV_RESULT_ACCEPTED
    peer.receive(of_type("HOME_POSITION"), timeout_s=0.5)   # at once, not at the 0.5 Hz stream
    peer.send(command_long(d.MAV_CMD_SET_MESSAGE_INTERVAL, float(d.MAVLINK_MSG_ID_ATTITUDE), 500_000.0))
    assert peer.receive(of_type("COMMAND_ACK")).result == d.MAV_RESULT_ACCEPTED
    received: list[int] = []
    parser = mavlink.FrameParser()
    for _ in range(500):   # 2 s of simulated time
        advance(0.004)
        try:
            while True:
                received += [f.msgid for f in parser.feed(peer.sock.recv(65536))]
        except TimeoutError:
            pass
    assert 3 <= received.count(d.MAVLINK_MSG_ID_ATTITUDE) <= 5


def test_keepalive_heartbeat_while_simulated_time_stands_still(free_instance: int) -> None:
    wall = [100.0]
    with StubHarness(WORLD, seed=12, ground_truth_estimate=True) as harness, \
            MavlinkApi(harness.autopilot, free_instance, gcs=False, clock=lambda: wall[0]) as api:
        peer = Peer(free_instance, api.pump)
        try:
            harness.run_for(0.1)
            api.pump()
            peer.receive(of_type("HEARTBEAT"), timeout_s=0.5)
            frozen = harness.autopilot.time_us
            wall[0] += 1.5   # held: no simulated time passes
            hb = peer.receive(of_type("HEARTBEAT"), timeout_s=0.5)
            assert hb.custom_mode == HOLD_CUSTOM_MODE
            assert harness.autopilot.time_us == frozen and api.stats.keepalives >= 1
        finally:
            peer.close()


def _datagrams(sock: socket.socket) -> list[list[int]]:
    """The message ids of every datagram waiting in `sock`, one list per datagram."""
    got = []
    while True:
        try:
            data = sock.recv(65536)
        except TimeoutError:
            return got
        got.append([f.msgid for f in mavlink.FrameParser().feed(data)])


def test_batched_telemetry_waits_for_its_wall_interval_or_a_held_pump(free_instance: int) -> None:
    wall = [100.0]
    with StubHarness(WORLD, seed=12, ground_truth_estimate=True) as harness, \
            MavlinkApi(harness.autopilot, free_instance, gcs=False, clock=lambda: wall[0], batch_wall_s=0.01) as api, \
            MavlinkApi(harness.autopilot, free_instance + 1, gcs=False, clock=lambda: wall[0]) as unbatched:
        peer, other = Peer(free_instance, api.pump), Peer(free_instance + 1, unbatched.pump)
        try:
            def run(steps: int) -> None:
                for _ in range(steps):
                    harness.run_for(0.004)
                    api.pump()
                    unbatched.pump()

            run(1)  # the first streams of both go out at once
            assert _datagrams(peer.sock) and _datagrams(other.sock)
            run(15)  # 60 ms simulated in no wall time: everything stays queued
            assert _datagrams(peer.sock) == []
            each_step = _datagrams(other.sock)
            assert len(each_step) >= 3  # one datagram per step with something due
            api.pump()  # held (simulated time unchanged): all of it, one datagram
            (batch,) = _datagrams(peer.sock)
            assert batch == [m for datagram in each_step for m in datagram]  # same messages, same order
            run(100)  # a long run without wall time: a datagram once BATCH_MAX_MESSAGES are queued
            sizes = [len(datagram) for datagram in _datagrams(peer.sock)]
            assert len(sizes) >= 2 and all(BATCH_MAX_MESSAGES <= n < 2 * BATCH_MAX_MESSAGES for n in sizes)
            api.pump()  # held: the rest
            _datagrams(peer.sock)
            run(10)
            assert _datagrams(peer.sock) == []
            wall[0] += 0.01  # the batch interval passed: the next running pump sends the queue
            run(1)
            assert len(_datagrams(peer.sock)) == 1
        finally:
            peer.close()
            other.close()


def test_reposition_flies_to_a_global_position_and_holds(vehicle) -> None:
    harness, api, peer, advance = vehicle
    ap = harness.autopilot
    peer.send(command_long(d.MAV_CMD_NAV_TAKEOFF))
    assert peer.receive(of_type("COMMAND_ACK")).result == d.MAV_RESULT_ACCEPTED
    peer.send(command_long(d.MAV_CMD_COMPONENT_ARM_DISARM, 1.0))
    assert peer.receive(of_type("COMMAND_ACK")).result == d.MAV_RESULT_ACCEPTED
    advance(5.0)   # armed in TAKEOFF: climbs, then holds
    lat0, lon0, alt0 = ap.estimate.origin
    target_lat = lat0 + math.degrees(3.0 / 6378137.0)   # 3 m north
    reposition = d.MAVLink_command_int_message(
        api.system_id, 1, d.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, d.MAV_CMD_DO_REPOSITION, 0, 0,
        -1.0, 1.0, 0.0, float("nan"), round(target_lat * 1e7), round(lon0 * 1e7), 4.0)
    peer.send(reposition)
    ack = peer.receive(lambda m: m.get_type() == "COMMAND_ACK" and m.command == d.MAV_CMD_DO_REPOSITION)
    assert ack.result == d.MAV_RESULT_ACCEPTED
    advance(8.0)
    north, east, down = ap.estimate.position_ned_m
    assert north == pytest.approx(3.0, abs=0.3) and abs(east) < 0.3
    assert -down == pytest.approx(4.0, abs=0.3)
    assert ap.custom_mode == HOLD_CUSTOM_MODE


def test_malformed_command_parameters_still_get_an_answer(vehicle) -> None:
    _, api, peer, _ = vehicle
    peer.send(command_long(d.MAV_CMD_DO_SET_MODE, float("nan"), float("inf")))
    assert peer.receive(of_type("COMMAND_ACK")).result == d.MAV_RESULT_UNSUPPORTED
    peer.send(command_long(d.MAV_CMD_COMPONENT_ARM_DISARM, float("nan")))
    assert peer.receive(of_type("COMMAND_ACK")).result == d.MAV_RESULT_DENIED
    assert not api.autopilot.armed
