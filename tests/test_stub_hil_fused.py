"""The stub's fused HIL step (`hil_fused`) against its per-message path: the same answers."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from sitl_bridge import mavlink
from sitl_bridge.autopilot.stub import HilClient, StubAutopilot
from sitl_bridge.autopilot.stub.modes import OFFBOARD, CommandResult
from sitl_bridge.hil.link import HilLink
from sitl_bridge.mavlink_kernels import actuator_values, float32_value, frame_crc
from sitl_bridge.physics import MotorCommand, Simulation
from sitl_bridge.physics.state import armed_command
from sitl_bridge.sensors import BaroSample, SensorSuite
from sitl_bridge.world.loader import load_world

d = mavlink.dialect
WORLD = load_world(Path(__file__).resolve().parents[1] / "worlds" / "empty.yaml")


class Socket:
    """What the HIL client sends, kept (no network)."""

    def __init__(self) -> None:
        self.sent: list[bytes] = []

    def send(self, data: bytes) -> int:
        self.sent.append(bytes(data))
        return len(data)


def client(fused: bool) -> HilClient:
    c = HilClient(StubAutopilot(0))
    c._sock = Socket()  # type: ignore[assignment]
    if not fused:
        c._fused = None
    return c


def step_bytes(link: HilLink, sensors: SensorSuite, sim: Simulation) -> bytes:
    """One lockstep step's messages as the simulator's link encodes them."""
    values = sensors.sample_values(sim.vehicle_vector(0), sim.time_us)
    data = link._encode_sensor(values, sim.time_us)
    if values[8] is not None:
        data += link._encode_gps(values[8], sim.time_us)
    return data


def test_float32_value_is_the_exact_widening() -> None:
    rng = np.random.default_rng(0)
    special = np.array(
        [0, 0x80000000, 1, 0x807FFFFF, 0x7F800000, 0xFF800000, 0x7F7FFFFF, 0x00800000], np.uint32
    )
    for bits in np.concatenate([special, rng.integers(0, 2**32, 5000, dtype=np.uint32)]):
        want = float(bits.view(np.float32))
        got = float32_value(int(bits))
        if math.isnan(want):
            assert math.isnan(got)
        else:
            assert got == want and math.copysign(1.0, got) == math.copysign(1.0, want)


def test_frame_crc_is_mavlinks_checksum() -> None:
    rng = np.random.default_rng(1)
    for n in (0, 1, 9, 74, 200):
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        assert frame_crc(data, 0, n, 47) == mavlink.crc_mcrf4xx(
            bytes((47,)), mavlink.crc_mcrf4xx(data)
        )


def test_fused_step_answers_the_same_bytes_from_boot_through_offboard_flight() -> None:
    """Cold boot, alignment, arming, takeoff, OFFBOARD velocity, a reboot in place (new controller
    vectors), takeoff again: the fused and per-message clients, fed the same simulator bytes,
    send the same frames and keep the same estimator state at every step (bit for bit), GPS
    and baro steps included."""
    sim = Simulation(WORLD, seed=3)
    sensors = SensorSuite(WORLD.home, seed=4, step_us=sim.step_us)
    link = object.__new__(HilLink)  # its encoding only, no server
    link._encoder = mavlink.FrameEncoder(1, 200)
    link._scratch, link._out = np.zeros(96, np.uint8), np.zeros(96, np.uint8)
    fused, per_message = client(True), client(False)
    pair = (fused, per_message)
    try:
        for i in range(2500):
            if i == 1900:  # flew; then a reboot in place (new controller vectors) and again
                assert sim.state(0).position_ned_m[2] < -1.0
                for c in pair:
                    c.autopilot.reset()
            if i in (900, 2200):
                for c in pair:
                    assert c.autopilot.arm() is CommandResult.ACCEPTED
                    assert c.autopilot.takeoff() is CommandResult.ACCEPTED
            if 1400 <= i < 1900 and i % 10 == 0:
                for c in pair:
                    c.autopilot.set_velocity_setpoint_ned((1.0, -0.5, -0.2))
                    if i == 1400:
                        assert c.autopilot.set_mode(*OFFBOARD) is CommandResult.ACCEPTED
            data = step_bytes(link, sensors, sim)
            assert [c._handle_bytes(data) for c in pair] == [1, 1]
            a, b = fused._sock.sent[-1], per_message._sock.sent[-1]  # type: ignore[union-attr]
            assert a == b, f"step {i}"
            np.testing.assert_array_equal(
                fused.autopilot.estimator.state, per_message.autopilot.estimator.state
            )
            values = mavlink.unpack_payload(mavlink.FrameParser().feed(a)[0])
            sim.step([armed_command(values[2:6]) if values[18] & 128 else MotorCommand.disarmed()])
        assert fused.autopilot.last_command == per_message.autopilot.last_command
        assert fused.stats == per_message.stats
        assert fused._parser.stats == per_message._parser.stats
        assert fused.stats.gps_msgs > 0 and sim.state(0).position_ned_m[2] < -0.5  # took off again
    finally:
        sim.close()


@pytest.mark.parametrize("case", ["split", "garbage", "state", "secondary", "signed", "two steps"])
def test_anything_unusual_declines_the_fused_step_and_changes_nothing(case: str) -> None:
    c = client(True)
    codec = mavlink.new_codec(1, 200)
    sensor = d.MAVLink_hil_sensor_message(
        4000, 0.0, 0.0, -9.81, 0.0, 0.0, 0.0, 0.21, 0.01, 0.43, 955.0, 0.0, 488.0, 15.0, 0x1BFF, 0
    ).pack(codec)
    data = {
        "split": sensor[:20],
        "garbage": b"\x00\x01" + sensor,
        "state": sensor
        + d.MAVLink_hil_state_quaternion_message(
            4000, [1, 0, 0, 0], 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0
        ).pack(codec),
        "secondary": d.MAVLink_hil_sensor_message(
            4000,
            0.0,
            0.0,
            -9.81,
            0.0,
            0.0,
            0.0,
            0.21,
            0.01,
            0.43,
            955.0,
            0.0,
            488.0,
            15.0,
            0x1BFF,
            1,
        ).pack(codec),
        "signed": sensor[:2] + b"\x01" + sensor[3:],
        "two steps": sensor + sensor,
    }[case]
    est = c.autopilot.estimator
    before = est.state.copy()
    taken: list[int] = []  # a declined step takes no sequence number
    assert c._fused is not None and c._fused.handle(data, lambda: taken.append(0) or 0) is None
    assert not taken
    np.testing.assert_array_equal(est.state, before)
    assert est.last_time_us is None and c.stats.sensor_msgs == 0 and not c._sock.sent  # type: ignore[union-attr]
    c._handle_bytes(data)  # the per-message path takes it
    assert c.stats.sensor_msgs == {"split": 0, "secondary": 0, "signed": 0, "two steps": 2}.get(
        case, 1
    )


def test_ground_truth_autopilots_keep_the_per_message_path() -> None:
    assert HilClient(StubAutopilot(0, ground_truth_estimate=True))._fused is None


def test_simulator_link_decodes_actuator_controls_like_the_frame_parser() -> None:
    """`actuator_values` (the link's compiled read) against the dialect's struct, truncated
    payloads, NaN and out-of-range controls included; anything but one whole frame declines."""
    rng = np.random.default_rng(2)
    encoder = mavlink.FrameEncoder(2, 1)
    scratch = np.zeros(96, np.uint8)
    cls = d.MAVLink_hil_actuator_controls_message
    for i in range(300):
        controls = [float(np.float32(x)) for x in rng.uniform(-0.5, 1.5, 16)]
        controls[4:] = [0.0] * 12 if i % 2 else controls[4:]
        if i % 7 == 0:
            controls[i % 4] = math.nan
        mode = (0, 1, 129)[i % 3]
        frame = encoder.pack(cls, 4000 * i, i % 3, *controls, mode)
        ok, time_usec, flags, got_mode, *u = actuator_values(frame, scratch)
        want = mavlink.unpack_payload(mavlink.FrameParser().feed(frame)[0])
        assert (ok, time_usec, flags, got_mode) == (1, want[0], want[1], want[18])
        assert str(u) == str(list(want[2:6]))  # NaN-aware, bit for bit as repr
        for bad in (
            frame[:-1],
            frame + frame,
            b"\x00" + frame,
            frame[:-1] + bytes((frame[-1] ^ 1,)),
        ):
            assert actuator_values(bad, scratch)[0] == 0


def test_simulator_link_encodes_hil_sensor_as_the_dialect_decodes_it() -> None:
    """`sensor_frame` (the link's compiled HIL_SENSOR) read back by the frame parser: float32 of
    the values clamped into PX4's ranges (NaN -> 0), fields_updated per group, id 0."""
    link = object.__new__(HilLink)
    link._encoder = mavlink.FrameEncoder(1, 200)
    link._scratch, link._out = np.zeros(96, np.uint8), np.zeros(96, np.uint8)
    rng = np.random.default_rng(3)
    for i in range(400):
        imu = [float(x) for x in rng.normal(0.0, 3.0 if i % 5 else 300.0, 6)]
        if i % 11 == 0:
            imu[i % 6] = math.nan
        mag = tuple(float(x) for x in rng.normal(0.0, 0.5 if i % 7 else 40.0, 3)) if i % 2 else None
        baro = BaroSample(950.0 + i, 15.0 - i, 500.0 * i) if i % 3 == 0 else None
        frames = mavlink.FrameParser().feed(link._encode_sensor((*imu, mag, baro, None), 4000 * i))
        assert len(frames) == 1 and frames[0].system_id == 1 and frames[0].component_id == 200
        got = mavlink.unpack_payload(frames[0])
        limits = [(-156.0, 156.0)] * 3 + [(-34.9, 34.9)] * 3 + [(-16.0, 16.0)] * 3
        values = imu + list(mag or (0.0, 0.0, 0.0))
        want = [
            0.0 if v != v else min(max(v, lo), hi)
            for v, (lo, hi) in zip(values, limits, strict=True)
        ]
        if baro is not None:
            want += [
                min(max(baro.pressure_hpa, 1.0), 1200.0),
                0.0,
                min(max(baro.pressure_alt_m, -1000.0), 50000.0),
                min(max(baro.temperature_c, -60.0), 85.0),
            ]
        else:
            want += [0.0] * 4
        fields = 0x3F | (0x1C0 if mag else 0) | (0x1A00 if baro else 0)
        assert got == (4000 * i, *[float(np.float32(w)) for w in want], fields, 0)
