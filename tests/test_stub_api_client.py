"""The stub's API link keeps its first client, like PX4's mavlink_receiver keeps its partner:
another local sender is answered at its own address but does not take the telemetry, until the
client has been silent for the heartbeat timeout. Real UDP sockets on both sides."""

from __future__ import annotations

import socket

from test_stub_api import WORLD, Peer, command_long, d, of_type, vehicle  # noqa: F401 (fixture)

from sitl_bridge import mavlink
from sitl_bridge.autopilot.stub import MavlinkApi
from sitl_bridge.autopilot.stub.harness import StubHarness
from sitl_bridge.autopilot.stub.mavlink_api import CLIENT_TIMEOUT_WALL_S

LOCAL_POSITION_NED = d.MAVLINK_MSG_ID_LOCAL_POSITION_NED


class Intruder:
    """Another local program on an ephemeral port that writes to the vehicle's API port."""

    def __init__(self, vehicle_address: tuple[str, int]) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.002)
        self.vehicle = vehicle_address
        self.codec = mavlink.new_codec(200, 1)
        self.received: list[int] = []

    def send(self, message) -> None:
        self.sock.sendto(message.pack(self.codec), self.vehicle)

    def heartbeat(self) -> None:
        self.send(d.MAVLink_heartbeat_message(d.MAV_TYPE_GCS, d.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3))

    def drain(self) -> list[mavlink.Frame]:
        frames = []
        while True:
            try:
                frames += mavlink.FrameParser().feed(self.sock.recv(65536))
            except TimeoutError:
                self.received += [f.msgid for f in frames]
                return frames


def _heartbeat(peer: Peer) -> None:
    peer.send(d.MAVLink_heartbeat_message(d.MAV_TYPE_GCS, d.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3))


def test_another_sender_does_not_take_the_clients_telemetry(vehicle) -> None:  # noqa: F811
    harness, api, peer, advance = vehicle
    intruder = Intruder(peer.vehicle)
    try:
        _heartbeat(peer)   # the client: MAVSDK's 1 Hz heartbeat
        peer.drain()
        peer.backlog = []
        seconds = 2.0
        for k in range(round(seconds / 0.1)):
            intruder.heartbeat()   # 10 Hz from another port
            if k % 10 == 9:
                _heartbeat(peer)
            advance(0.1)
            intruder.drain()
        received = peer.backlog + peer.drain()
        rate = sum(m.get_type() == "LOCAL_POSITION_NED" for m in received) / seconds
        assert rate >= 28.0, f"client got LOCAL_POSITION_NED at {rate:.1f}/s"   # the 30 Hz stream
        assert LOCAL_POSITION_NED not in intruder.received
        # the other sender's command is executed and answered at its own address
        intruder.send(command_long(d.MAV_CMD_REQUEST_MESSAGE, float(d.MAVLINK_MSG_ID_AUTOPILOT_VERSION)))
        advance(0.02)
        answered = [f.msgid for f in intruder.drain()]
        assert d.MAVLINK_MSG_ID_COMMAND_ACK in answered and d.MAVLINK_MSG_ID_AUTOPILOT_VERSION in answered
        assert not any(m.get_type() == "AUTOPILOT_VERSION" for m in peer.drain())
    finally:
        intruder.sock.close()


def test_the_link_hands_over_after_the_client_is_silent_for_the_timeout(free_instance: int) -> None:
    wall = [100.0]
    with StubHarness(WORLD, seed=12, ground_truth_estimate=True) as harness, \
            MavlinkApi(harness.autopilot, free_instance, gcs=False, clock=lambda: wall[0]) as api:
        peer = Peer(free_instance, api.pump)
        intruder = Intruder(peer.vehicle)
        try:
            def run(seconds: float) -> None:
                for _ in range(round(seconds / 0.004)):
                    harness.run_for(0.004)
                    api.pump()

            _heartbeat(peer)
            run(0.2)
            peer.receive(of_type("LOCAL_POSITION_NED"), timeout_s=0.5)
            wall[0] += CLIENT_TIMEOUT_WALL_S - 0.5   # the client is quiet, but not for long enough
            intruder.heartbeat()
            run(0.2)
            assert LOCAL_POSITION_NED not in [f.msgid for f in intruder.drain()]
            wall[0] += 0.6   # now silent for longer than the timeout: the next sender takes over
            intruder.heartbeat()
            run(0.2)
            assert LOCAL_POSITION_NED in [f.msgid for f in intruder.drain()]
            peer.drain()
            run(0.2)
            assert not any(m.get_type() == "LOCAL_POSITION_NED" for m in peer.drain())
        finally:
            intruder.sock.close()
            peer.close()
