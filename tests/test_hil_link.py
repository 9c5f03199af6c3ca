"""Protocol tests of the simulator link against an independent autopilot-side peer.

The peer below is written from the MAVLink definitions, not from sitl_bridge: its own TCP
client and pymavlink's own parser (not sitl_bridge's fast codec). The simulator side is the
real thing: pybullet physics, the sensor suite, `HilLink`, `Lockstep`.
"""

from __future__ import annotations

import logging
import math
import os
import random
import socket
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as mav  # noqa: E402

from sitl_bridge import mavlink  # noqa: E402
from sitl_bridge.hil import HilError, HilLink, LinkClosed, Lockstep, LockstepTimeout  # noqa: E402
from sitl_bridge.physics.simulation import Simulation  # noqa: E402
from sitl_bridge.sensors.suite import SensorSuite  # noqa: E402
from sitl_bridge.world.loader import load_world  # noqa: E402

WORLDS = Path(__file__).resolve().parents[1] / "worlds"
STEP_US = 4000


class _Sink:
    def write(self, data: bytes) -> None:
        pass


class Peer:
    """Autopilot side: TCP client + pymavlink parser, like PX4's simulator_mavlink."""

    def __init__(self, port: int, system_id: int = 1) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=5)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.codec = mav.MAVLink(_Sink(), srcSystem=system_id, srcComponent=1)
        self.codec.robust_parsing = True
        self.received: list = []
        self.answer = True
        self.armed = False
        self.controls = [0.0] * 16

    def send(self, message) -> None:
        self.sock.sendall(message.pack(self.codec))

    def greet(self, state_interval_us: float = 5000.0) -> None:
        """PX4's first bytes: SET_MESSAGE_INTERVAL(115) and one HEARTBEAT."""
        self.send(mav.MAVLink_command_long_message(0, 0, mav.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                                   115, state_interval_us, 0, 0, 0, 0, 0))
        self.send(mav.MAVLink_heartbeat_message(0, mav.MAV_AUTOPILOT_PX4, 0, 0, 0, 3))

    def actuators(self, time_usec: int, controls=None, armed=None) -> mav.MAVLink_message:
        armed = self.armed if armed is None else armed
        mode = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mav.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
        return mav.MAVLink_hil_actuator_controls_message(
            time_usec, list(controls or self.controls), mode, 1)

    def pump(self) -> None:
        """Read without blocking; answer each HIL_SENSOR id 0 (a Lockstep pump)."""
        self.sock.setblocking(False)
        try:
            data = self.sock.recv(1 << 16)
        except BlockingIOError:
            return
        finally:
            self.sock.setblocking(True)
        for message in self.codec.parse_buffer(data) or []:
            self.received.append(message)
            if message.get_type() == "HIL_SENSOR" and message.id == 0 and self.answer:
                self.send(self.actuators(message.time_usec))

    def close(self) -> None:
        self.sock.close()

    def of_type(self, name: str) -> list:
        return [m for m in self.received if m.get_type() == name]


@pytest.fixture
def rig(free_instance):
    """One Iris at rest in the empty world, its link and a connected, greeting peer."""
    world = load_world(WORLDS / "empty.yaml")
    sim = Simulation(world)
    sensors = [SensorSuite(world.home, seed=1)]
    link = HilLink(free_instance)
    peer = Peer(link.port)
    peer.greet()  # a peer becomes the autopilot once it speaks (PX4's first bytes)
    assert link.accept(5.0)
    lockstep = Lockstep(sim, sensors, [link], speed_factor=0, pumps=[peer.pump], actuator_timeout_s=5.0)
    yield sim, sensors, link, peer, lockstep
    peer.close()
    link.close()
    sim.close()


def test_stream_at_rest_has_px4_units_and_rates(rig):
    sim, _, link, peer, lockstep = rig
    lockstep.run_for(2.0)
    peer.pump()
    sensor = peer.of_type("HIL_SENSOR")
    assert len(sensor) == 500 == link.stats.sensor_msgs  # exactly one per 4 ms step
    assert all(m.id == 0 for m in sensor)
    times = [m.time_usec for m in sensor]
    assert all(b - a == STEP_US for a, b in zip(times, times[1:], strict=False))
    assert times[0] > 0
    # specific force at rest, body FRD: about -g on z
    z = sum(m.zacc for m in sensor[100:]) / len(sensor[100:])
    assert -10.1 < z < -9.5
    assert all(abs(m.xacc) < 1.0 and abs(m.yacc) < 1.0 for m in sensor[100:])
    assert all(abs(m.xgyro) < 0.2 for m in sensor[100:])
    allowed = {0x3F, 0x3F | 0x1C0, 0x3F | 0x1A00, 0x3F | 0x1C0 | 0x1A00}
    assert {m.fields_updated for m in sensor} <= allowed
    mags = [m for m in sensor if m.fields_updated & 0x1C0 == 0x1C0]
    baros = [m for m in sensor if m.fields_updated & 0x1A00 == 0x1A00]
    assert 140 <= len(mags) <= 210  # ~100 Hz nominal (83 Hz on 4 ms steps)
    assert 70 <= len(baros) <= 105  # ~50 Hz nominal
    total = [math.sqrt(m.xmag**2 + m.ymag**2 + m.zmag**2) for m in mags]
    assert 0.45 < sum(total) / len(total) < 0.51  # gauss, WMM at Zurich
    pressure = sum(m.abs_pressure for m in baros) / len(baros)
    assert 950.0 < pressure < 960.0  # hPa at 488 m AMSL
    assert all(0.0 < m.temperature < 20.0 for m in baros)  # ISA at 488 m: about 11.8 C
    # GPS at 5 Hz, each right after the HIL_SENSOR it shares time_usec with
    order = [m.get_type() for m in peer.received]
    gps = peer.of_type("HIL_GPS")
    assert 9 <= len(gps) <= 11
    for index, name in enumerate(order):
        if name == "HIL_GPS":
            before = [m for m in peer.received[:index] if m.get_type() == "HIL_SENSOR"][-1]
            assert peer.received[index].time_usec == before.time_usec
    gaps = [b.time_usec - a.time_usec for a, b in zip(gps, gps[1:], strict=False)]
    assert all(gap == 200_000 for gap in gaps)
    fix = gps[-1]
    assert fix.fix_type == 3 and fix.satellites_visible >= 6
    assert abs(fix.lat - 473977420) < 100 and abs(fix.lon - 85455940) < 100  # degE7
    assert abs(fix.alt - 488_000) < 500  # mm AMSL
    assert fix.eph <= 300 and fix.epv <= 500  # cm
    # ground truth at the requested 5000 us (200 Hz average), a unit quaternion
    state = peer.of_type("HIL_STATE_QUATERNION")
    assert 395 <= len(state) <= 405
    q = state[-1].attitude_quaternion
    assert abs(math.sqrt(sum(c * c for c in q)) - 1.0) < 1e-4
    assert abs(q[0]) > 0.99  # spawned level, facing north: NED-FRD identity
    assert link.heartbeat is not None and link.heartbeat.autopilot == mav.MAV_AUTOPILOT_PX4


def test_actuators_map_to_motor_commands(rig):
    sim, sensors, link, peer, lockstep = rig
    lockstep.pumps.clear()
    frame = sensors[0].sample(sim.state(0), sim.time_us)
    link.send_sensor_frame(frame)
    wire = link.last_sent_time_usec
    peer.send(peer.actuators(wire, [0.6, 0.7, 1.5, -0.2] + [0.9] * 12, armed=True))
    command = link.receive_actuators(frame.time_us, 2.0)
    assert command.armed
    assert command.controls == pytest.approx((0.6, 0.7, 1.0, 0.0))  # clamped to [0, 1]
    frame = sensors[0].sample(sim.state(0), sim.time_us + STEP_US)
    link.send_sensor_frame(frame)
    peer.send(peer.actuators(link.last_sent_time_usec, [0.6] * 16, armed=False))
    command = link.receive_actuators(frame.time_us, 2.0)
    assert not command.armed and command.controls == (0.0, 0.0, 0.0, 0.0)


def test_values_are_clamped_to_px4_ranges(rig):
    sim, sensors, link, peer, lockstep = rig
    lockstep.pumps.clear()
    frame = sensors[0].sample(sim.state(0), sim.time_us)
    frame.accel_frd_m_s2 = np.array([500.0, -500.0, float("nan")])  # a crash: beyond 16 g
    frame.gyro_frd_rad_s = np.array([100.0, -100.0, 1.0])  # beyond 2000 deg/s
    link.send_sensor_frame(frame)
    deadline = time.monotonic() + 5
    while not peer.of_type("HIL_SENSOR") and time.monotonic() < deadline:
        peer.pump()
    (message,) = peer.of_type("HIL_SENSOR")
    assert (message.xacc, message.yacc, message.zacc) == (156.0, -156.0, 0.0)
    assert message.xgyro == pytest.approx(34.9) and message.ygyro == pytest.approx(-34.9)
    assert message.zgyro == pytest.approx(1.0)


def test_an_answer_stamped_in_the_future_answers_no_later_step(rig):
    sim, sensors, link, peer, lockstep = rig
    lockstep.run_for(0.1)
    assert link.actuators_flowing
    handled = link.stats.actuator_msgs
    peer.send(peer.actuators(2**62))   # a bogus time, far ahead of any step sent
    deadline = time.monotonic() + 5
    while link.stats.actuator_msgs == handled and time.monotonic() < deadline:
        link.poll()
    link.send_sensor_frame(sensors[0].sample(sim.state(0), sim.time_us + sim.step_us))
    assert not link.answered(), "the lockstep would no longer wait for the autopilot"
    lockstep.run_for(0.1)   # and it still runs in step with the real answers
    assert lockstep.stats.timeouts == 0 and link.answered()


def test_garbage_and_split_frames_do_not_stop_the_link(rig):
    sim, sensors, link, peer, lockstep = rig
    lockstep.pumps.clear()
    rng = random.Random(7)
    for step in range(20):
        frame = sensors[0].sample(sim.state(0), sim.time_us + step * STEP_US)
        link.send_sensor_frame(frame)
        data = bytes(peer.actuators(link.last_sent_time_usec, [0.25] * 16, armed=True).pack(peer.codec))
        garbage = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 40)))
        chunks = [garbage + data[:5], data[5:17], data[17:]]
        for chunk in chunks:
            peer.sock.sendall(chunk)
            link.poll()  # partial frames arrive between reads
        assert link.receive_actuators(frame.time_us, 2.0).controls == (0.25,) * 4
    assert link.stats.garbage_bytes > 0
    assert link.stats.actuator_msgs == 20


def test_timeout_is_reported(rig):
    sim, _, link, peer, lockstep = rig
    lockstep.actuator_timeout_s = 0.2
    lockstep.run_for(0.2)
    peer.answer = False
    time_before = sim.time_us
    with pytest.raises(LockstepTimeout) as raised:
        lockstep.step()
    assert raised.value.instances == (link.instance,)
    assert sim.time_us == time_before  # the step did not advance
    assert lockstep.stats.timeouts == 1 and link.stats.timeouts == 1


def _ground_truth_after_asking(peer, lockstep, interval_us: float, run_s: float) -> int:
    """HIL_STATE_QUATERNION messages in `run_s` after the peer asked for `interval_us`."""
    peer.send(mav.MAVLink_command_long_message(0, 0, mav.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                               115, interval_us, 0, 0, 0, 0, 0))
    lockstep.run_for(0.04)
    peer.received.clear()
    lockstep.run_for(run_s)
    peer.pump()
    assert peer.of_type("HIL_SENSOR")
    return len(peer.of_type("HIL_STATE_QUATERNION"))


def test_set_message_interval_controls_ground_truth(rig):
    _, _, _, peer, lockstep = rig
    assert _ground_truth_after_asking(peer, lockstep, -1, 0.4) == 0
    assert 49 <= _ground_truth_after_asking(peer, lockstep, 20000, 1.0) <= 51  # 50 Hz


def test_a_link_without_ground_truth_ignores_the_autopilots_request(rig):
    """`HilLink(ground_truth=False)` (PX4 with its logger off: nothing reads the ground truth)."""
    _, _, link, peer, lockstep = rig
    link.ground_truth, link.state_interval_us = False, -1
    assert _ground_truth_after_asking(peer, lockstep, 5000, 0.4) == 0


def test_px4_reads_hil_ground_truth_only_when_it_logs(tmp_path):
    from sitl_bridge.autopilot.fleet import FleetConfig
    from sitl_bridge.autopilot.px4.fleet import Px4SitlFleet
    from sitl_bridge.world import load_world

    world = load_world(Path(__file__).resolve().parents[1] / "worlds" / "empty.yaml")
    assert not Px4SitlFleet(FleetConfig(world=world, instances=(0,))).reads_hil_ground_truth  # SDLOG_MODE -1
    logging = FleetConfig(world=world, instances=(0,), params={"SDLOG_MODE": 0})
    assert Px4SitlFleet(logging).reads_hil_ground_truth


def test_closed_connection_and_reconnect(rig):
    sim, _, link, peer, lockstep = rig
    lockstep.run_for(0.1)
    last_time = link.last_sent_time_usec
    lockstep.pumps.clear()
    peer.close()
    with pytest.raises(LinkClosed):
        for _ in range(100):
            lockstep.step()
    assert not link.connected
    # A new autopilot (a restarted PX4) connects; time on the wire never goes back, even
    # after the simulation is reset in place.
    second = Peer(link.port)
    try:
        second.greet()
        assert link.accept(5.0)
        sim.reset()
        lockstep.pumps[:] = [second.pump]
        lockstep.run_for(0.1)
        second.pump()
        times = [m.time_usec for m in second.of_type("HIL_SENSOR")]
        assert times[0] > last_time
        assert all(b - a == STEP_US for a, b in zip(times, times[1:], strict=False))
    finally:
        second.close()


def test_port_in_use_is_a_clear_error(free_instance):
    with HilLink(free_instance), pytest.raises(HilError, match="cannot listen"):
        HilLink(free_instance)


def test_accept_times_out_without_autopilot(free_instance):
    with HilLink(free_instance) as link:
        start = time.monotonic()
        assert not link.accept(0.1)
        assert time.monotonic() - start < 2.0


# -- the fast codec against pymavlink -----------------------------------------------------------
def test_fast_encoder_frames_parse_in_pymavlink():
    encoder = mavlink.FrameEncoder(1, 200)
    data = encoder.pack(mav.MAVLink_hil_sensor_message, 123456, 0.1, -0.2, -9.8, 0.01, 0.02, 0.03,
                        0.2, 0.01, 0.43, 955.0, 0.0, 488.0, 12.0, 7167, 0)
    codec = mav.MAVLink(_Sink())
    (message,) = codec.parse_buffer(data)
    assert message.time_usec == 123456 and message.zacc == pytest.approx(-9.8)
    assert message.fields_updated == 7167 and message.id == 0
    assert message.get_srcSystem() == 1 and message.get_srcComponent() == 200


@settings(max_examples=60, deadline=None)
@given(st.lists(st.binary(max_size=60), max_size=8), st.integers(min_value=1, max_value=17))
def test_parser_survives_garbage_and_any_split(garbage, chunk):
    codec = mav.MAVLink(_Sink(), srcSystem=3, srcComponent=1)
    frames = [bytes(mav.MAVLink_hil_actuator_controls_message(t, [0.5] * 16, 129, 1).pack(codec))
              for t in range(1, len(garbage) + 2)]
    stream = b"".join(g + f for g, f in zip(garbage + [b""], frames, strict=False))
    parser = mavlink.FrameParser()
    got = []
    for start in range(0, len(stream), chunk):
        got += parser.feed(stream[start:start + chunk])
    times = [mavlink.unpack_payload(f)[0] for f in got if f.msgid == mavlink.HIL_ACTUATOR_CONTROLS]
    # Every real frame is recovered, in order: a fake header in the garbage fails its CRC and
    # costs one byte of resynchronisation, never a real frame.
    assert times == list(range(1, len(frames) + 1))


def _raw_connection(port: int) -> socket.socket:
    return socket.create_connection(("127.0.0.1", port), timeout=5)


def test_a_peer_sending_garbage_first_does_not_become_the_autopilot(free_instance, caplog):
    with HilLink(free_instance) as link:
        intruder = _raw_connection(link.port)
        intruder.sendall(b"GET / HTTP/1.1\r\n" + bytes(range(256)) * 20)
        assert not link.accept(0.3)  # garbage is no autopilot
        real = Peer(link.port)
        try:
            real.greet()
            with caplog.at_level(logging.WARNING):
                assert link.accept(5.0)
            assert link.heartbeat is not None and link.heartbeat.autopilot == mav.MAV_AUTOPILOT_PX4
            assert link.peer == f"127.0.0.1:{real.sock.getsockname()[1]}"
            assert any("dropped a connection" in r.getMessage() for r in caplog.records)
            intruder.settimeout(2.0)
            assert intruder.recv(1) == b""  # the intruder was disconnected
        finally:
            real.close()
            intruder.close()


def test_a_stale_idle_connection_is_never_taken(free_instance):
    with HilLink(free_instance) as link:
        first = Peer(link.port)
        first.greet()
        assert link.accept(5.0)
        stale = _raw_connection(link.port)  # queued while the first autopilot runs, never speaks
        link.disconnect()
        first.close()
        assert not link.accept(0.3)  # a reset's accept: the idle peer is not an autopilot
        restarted = Peer(link.port)
        try:
            restarted.greet()
            assert link.accept(5.0)
            assert link.peer == f"127.0.0.1:{restarted.sock.getsockname()[1]}"
        finally:
            restarted.close()
            stale.close()


def test_a_silent_peer_is_dropped_after_the_silence_limit(free_instance, monkeypatch):
    from sitl_bridge.hil import admission

    monkeypatch.setattr(admission, "SILENCE_LIMIT_S", 0.2)
    with HilLink(free_instance) as link:
        silent = _raw_connection(link.port)
        try:
            assert not link.accept(0.6)
            silent.settimeout(2.0)
            assert silent.recv(1) == b""
        finally:
            silent.close()
