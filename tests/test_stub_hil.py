"""The stub's HIL client against a simulator-side peer, in lockstep, over real TCP."""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from sitl_bridge import mavlink
from sitl_bridge.autopilot.stub import HilClient, StubAutopilot, StubVehicle
from sitl_bridge.autopilot.stub.hil_client import PX4_STATE_INTERVAL_US
from sitl_bridge.autopilot.stub.modes import HOLD, CommandResult
from sitl_bridge.hil.link import HilLink
from sitl_bridge.hil.lockstep import Lockstep
from sitl_bridge.physics import Simulation
from sitl_bridge.sensors import SensorSuite
from sitl_bridge.world.loader import load_world

d = mavlink.dialect
WORLD = load_world(Path(__file__).resolve().parents[1] / "worlds" / "empty.yaml")
HIL_BASE_PORT = 4560


class SimulatorPeer:
    """A minimal simulator: TCP server on 4560+i, pymavlink-encoded HIL messages."""

    def __init__(self, instance: int) -> None:
        self.server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.server.bind(("127.0.0.1", HIL_BASE_PORT + instance))
        self.server.listen(1)
        self.conn: socket.socket | None = None
        self.codec = mavlink.new_codec(1, 200)
        self.parser = mavlink.FrameParser()

    def accept(self) -> None:
        self.server.settimeout(2.0)
        self.conn, _ = self.server.accept()
        self.conn.settimeout(0.2)

    def sensor(self, time_usec: int, sensor_id: int = 0, fields: int = 0x1BFF) -> bytes:
        msg = d.MAVLink_hil_sensor_message(time_usec, 0.0, 0.0, -9.81, 0.0, 0.0, 0.0, 0.21, 0.01, 0.43,
                                           955.0, 0.0, 488.0, 15.0, fields, sensor_id)
        return msg.pack(self.codec)

    def frames(self, timeout_s: float = 0.2) -> list[mavlink.Frame]:
        """Whatever frames arrive within timeout_s."""
        assert self.conn is not None
        out: list[mavlink.Frame] = []
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                data = self.conn.recv(65536)
            except TimeoutError:
                break
            if not data:
                break
            out += self.parser.feed(data)
        return out

    def close(self) -> None:
        if self.conn is not None:
            self.conn.close()
        self.server.close()


@pytest.fixture
def peer_and_client(free_instance: int):
    peer = SimulatorPeer(free_instance)
    client = HilClient(StubAutopilot(free_instance), free_instance, state_interval_us=PX4_STATE_INTERVAL_US)
    try:
        assert client.connect(2.0)
        peer.accept()
        yield peer, client
    finally:
        client.close()
        peer.close()


def actuator_answers(frames: list[mavlink.Frame]) -> list[tuple]:
    return [mavlink.unpack_payload(f) for f in frames if f.msgid == d.MAVLINK_MSG_ID_HIL_ACTUATOR_CONTROLS]


def test_connect_sends_heartbeat_and_state_interval_request_like_px4(peer_and_client) -> None:
    peer, client = peer_and_client
    frames = peer.frames()
    kinds = [f.msgid for f in frames]
    assert kinds.count(d.MAVLINK_MSG_ID_HEARTBEAT) == 1
    assert kinds.count(d.MAVLINK_MSG_ID_COMMAND_LONG) == 1
    command = next(mavlink.unpack_payload(f) for f in frames if f.msgid == d.MAVLINK_MSG_ID_COMMAND_LONG)
    assert command[7] == d.MAV_CMD_SET_MESSAGE_INTERVAL
    assert command[0] == d.MAVLINK_MSG_ID_HIL_STATE_QUATERNION and command[1] == 5000
    heartbeat = next(mavlink.unpack_payload(f) for f in frames if f.msgid == d.MAVLINK_MSG_ID_HEARTBEAT)
    assert heartbeat[2] == d.MAV_AUTOPILOT_PX4


def test_every_sensor_message_gets_exactly_one_answer_with_its_time(peer_and_client) -> None:
    peer, client = peer_and_client
    peer.frames()
    for k in range(1, 6):
        t = 1_000_000 + 4000 * k
        peer.conn.sendall(peer.sensor(t))
        time.sleep(0.01)
        assert client.pump() == 1
        answers = actuator_answers(peer.frames(0.05))
        assert len(answers) == 1
        time_usec, flags, *controls, mode = answers[0]
        assert time_usec == t and flags == 1
        assert mode == d.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED   # disarmed: no SAFETY_ARMED bit
        assert controls == [0.0] * 16
    assert client.stats.sensor_msgs == client.stats.actuator_msgs == 5


def test_split_frames_garbage_and_secondary_sensors(peer_and_client) -> None:
    peer, client = peer_and_client
    peer.frames()
    data = peer.sensor(2_000_000)
    peer.conn.sendall(data[:20])
    time.sleep(0.01)
    assert client.pump() == 0          # half a frame: nothing to answer yet
    peer.conn.sendall(data[20:])
    time.sleep(0.01)
    assert client.pump() == 1
    peer.conn.sendall(b"\x00garbage\xfd\x01" + peer.sensor(2_004_000, sensor_id=1) + peer.sensor(2_008_000))
    time.sleep(0.01)
    assert client.pump() == 1          # id 1 does not drive the clock; id 0 is answered
    answers = actuator_answers(peer.frames(0.05))
    assert [a[0] for a in answers] == [2_000_000, 2_008_000]
    assert client.stats.garbage_bytes > 0


def test_stub_flies_in_lockstep_through_the_real_hil_link(free_instance: int) -> None:
    sim = Simulation(WORLD, seed=0)
    suite = SensorSuite(WORLD.home, seed=1, step_us=sim.step_us)
    link = HilLink(free_instance, step_us=sim.step_us)
    vehicle = StubVehicle(free_instance, ground_truth_estimate=True, api=False)
    try:
        assert vehicle.connect(2.0) and link.accept(2.0)
        lockstep = Lockstep(sim, [suite], [link], speed_factor=0, pumps=[vehicle.pump])
        lockstep.run_for(0.5)
        ap = vehicle.autopilot
        assert ap.arm() is CommandResult.ACCEPTED and ap.takeoff() is CommandResult.ACCEPTED
        lockstep.run_for(6.0)
        assert link.command.armed
        assert (ap.commander.main_mode, ap.commander.sub_mode) == HOLD
        assert -sim.state(0).position_ned_m[2] == pytest.approx(2.5 + 0.06, abs=0.3)
        assert link.stats.actuator_msgs == link.stats.sensor_msgs == vehicle.hil.stats.sensor_msgs
        assert link.stats.stale_actuator_msgs == 0 and lockstep.stats.timeouts == 0
        assert vehicle.hil.stats.state_msgs == link.stats.sensor_msgs   # ground truth every step
    finally:
        vehicle.close()
        link.close()
        sim.close()


def test_stub_command_runs_as_its_own_process(free_instance: int) -> None:
    sim = Simulation(WORLD, seed=0)
    suite = SensorSuite(WORLD.home, seed=1, step_us=sim.step_us)
    link = HilLink(free_instance, step_us=sim.step_us)
    api_peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    api_peer.bind(("127.0.0.1", 14540 + free_instance))
    api_peer.settimeout(0.1)
    process = subprocess.Popen(
        [sys.executable, "-m", "sitl_bridge", "stub", "-i", str(free_instance), "--once", "--no-gcs"],
        stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        assert link.accept(20.0), "the stub process never connected"
        lockstep = Lockstep(sim, [suite], [link], speed_factor=0, actuator_timeout_s=5.0)
        lockstep.run_for(2.0)
        assert link.actuators_flowing and lockstep.stats.timeouts == 0
        assert link.stats.actuator_msgs >= 490
        assert link.state_interval_us == -1   # estimating from sensors: no ground truth asked for
        codec = mavlink.new_codec(245, 190)
        heartbeat = None
        deadline = time.monotonic() + 5.0
        while heartbeat is None and time.monotonic() < deadline:
            lockstep.run_for(0.1)
            try:
                frames = mavlink.FrameParser().feed(api_peer.recv(65536))
            except TimeoutError:
                continue
            heartbeat = next((mavlink.decode_frame(codec, f) for f in frames
                              if f.msgid == d.MAVLINK_MSG_ID_HEARTBEAT), None)
        assert heartbeat is not None and heartbeat.autopilot == d.MAV_AUTOPILOT_PX4
        link.close()   # the simulator goes away: a --once stub exits cleanly
        assert process.wait(timeout=10) == 0
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        if process.stdout is not None:
            process.stdout.close()
        api_peer.close()
        link.close()
        sim.close()
