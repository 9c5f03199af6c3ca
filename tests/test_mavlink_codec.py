"""The fast MAVLink 2 codec (`sitl_bridge.mavlink`) against pymavlink, byte for byte.

Every message the simulator link and the stub's API send or receive per step is packed by
`FrameEncoder` and split by `FrameParser` (its whole-frame fast path and its general path);
pymavlink, imported directly here, is the reference: the same frame bytes for random values
(MAVLink 2 header, trailing-zero truncation, CRC with CRC_EXTRA), and the same values back.
"""

from __future__ import annotations

import os
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as mav  # noqa: E402

from sitl_bridge import mavlink  # noqa: E402
from sitl_bridge.autopilot.stub import hil_client  # noqa: E402

# the per-step messages of the simulator link and the stub's telemetry streams
HOT = [
    mav.MAVLink_hil_sensor_message, mav.MAVLink_hil_gps_message, mav.MAVLink_hil_state_quaternion_message,
    mav.MAVLink_hil_actuator_controls_message, mav.MAVLink_heartbeat_message, mav.MAVLink_command_long_message,
    mav.MAVLink_attitude_message, mav.MAVLink_attitude_quaternion_message, mav.MAVLink_local_position_ned_message,
    mav.MAVLink_global_position_int_message, mav.MAVLink_gps_raw_int_message, mav.MAVLink_sys_status_message,
    mav.MAVLink_extended_sys_state_message, mav.MAVLink_battery_status_message,
    mav.MAVLink_set_position_target_local_ned_message,
]

_INTS = {"int8_t": 8, "int16_t": 16, "int32_t": 32, "int64_t": 64}
_UINTS = {"uint8_t": 8, "uint16_t": 16, "uint32_t": 32, "uint64_t": 64}


class _Sink:
    def write(self, data: bytes) -> None:
        pass


def _value(kind: str) -> st.SearchStrategy:
    """One field value; zeros are frequent so that payloads end in zero bytes (truncation)."""
    if kind == "float":
        drawn = st.floats(width=32, allow_nan=False, allow_infinity=False)
    elif kind in _UINTS:
        drawn = st.integers(0, 2 ** _UINTS[kind] - 1)
    elif kind in _INTS:
        bits = _INTS[kind]
        drawn = st.integers(-(2 ** (bits - 1)), 2 ** (bits - 1) - 1)
    else:  # pragma: no cover - the hot messages carry no other types
        raise AssertionError(kind)
    return st.one_of(st.just(0.0 if kind == "float" else 0), drawn)


@st.composite
def _message(draw: st.DrawFn) -> tuple[type, dict, list]:
    """(message class, constructor fields, wire-order values with arrays flattened)."""
    cls = draw(st.sampled_from(HOT))
    kinds = dict(zip(cls.fieldnames, cls.fieldtypes, strict=True))
    fields: dict = {}
    for name, length in zip(cls.ordered_fieldnames, cls.array_lengths, strict=True):
        if length:
            fields[name] = [draw(_value(kinds[name])) for _ in range(length)]
        else:
            fields[name] = draw(_value(kinds[name]))
    wire: list = []
    for name in cls.ordered_fieldnames:
        value = fields[name]
        wire.extend(value) if isinstance(value, list) else wire.append(value)
    return cls, fields, wire


def _pymavlink_frame(cls: type, fields: dict, seq: int, sysid: int, compid: int) -> bytes:
    codec = mav.MAVLink(_Sink(), srcSystem=sysid, srcComponent=compid)
    codec.seq = seq
    return bytes(cls(**{name: fields[name] for name in cls.fieldnames}).pack(codec))


@settings(max_examples=400, deadline=None)
@given(_message(), st.integers(0, 255), st.integers(1, 255), st.integers(0, 255))
def test_frames_are_pymavlinks_bytes_and_parse_back(message, seq, sysid, compid):
    cls, fields, wire = message
    encoder = mavlink.FrameEncoder(sysid, compid)
    encoder.sequence = seq
    ours = encoder.pack(cls, *wire)
    assert ours == _pymavlink_frame(cls, fields, seq, sysid, compid)
    assert encoder.sequence == (seq + 1) & 0xFF

    (frame,) = mavlink.FrameParser().feed(ours)
    assert (frame.msgid, frame.system_id, frame.component_id, frame.sequence) == (cls.id, sysid, compid, seq)
    assert frame.raw == ours and len(frame.payload) == cls.unpacker.size  # zero-extended
    expected = cls.unpacker.unpack(cls.unpacker.pack(*wire))  # the wire's float32 rounding
    assert mavlink.unpack_payload(frame) == expected
    decoded = mavlink.decode_frame(mavlink.new_codec(1, 1), frame)
    assert decoded.get_msgId() == cls.id and decoded.get_seq() == seq


@settings(max_examples=100, deadline=None)
@given(st.lists(_message(), min_size=1, max_size=6), st.binary(max_size=20), st.integers(1, 40))
def test_several_frames_in_one_read_or_split_anywhere(messages, garbage, chunk):
    encoder = mavlink.FrameEncoder(1, 200)
    frames = [encoder.pack(cls, *wire) for cls, _, wire in messages]
    stream = b"".join(frames)
    # one read holding a step's messages: all of them, in order (the fast path)
    assert [f.raw for f in mavlink.FrameParser().feed(stream)] == frames
    # behind garbage and cut into chunks: the same frames (the general path)
    parser = mavlink.FrameParser()
    noisy = garbage.replace(b"\xfd", b"").replace(b"\xfe", b"") + stream
    got = []
    for start in range(0, len(noisy), chunk):
        got += parser.feed(noisy[start:start + chunk])
    assert [f.raw for f in got] == frames
    assert parser.stats.frames == len(frames)


def test_a_bad_checksum_is_counted_and_the_next_frame_still_parses():
    encoder = mavlink.FrameEncoder(1, 200)
    good = encoder.pack(mav.MAVLink_heartbeat_message, 0, 2, 12, 81, 3, 3)
    broken = bytearray(encoder.pack(mav.MAVLink_heartbeat_message, 0, 2, 12, 81, 3, 3))
    broken[-1] ^= 0xFF
    parser = mavlink.FrameParser()
    assert [f.raw for f in parser.feed(bytes(broken) + good)] == [good]
    assert parser.stats.bad_crc == 1 and parser.stats.frames == 1


@pytest.mark.parametrize("armed", [True, False])
def test_the_stubs_short_actuator_layout_is_the_dialects(armed):
    """The stub answers with a 4-motor struct ("<QQ4f48xB"): the same bytes as the full message."""
    controls = [0.25, 0.5, 0.75, 1.0] if armed else [0.0] * 4
    mode = 129 if armed else 1
    short = hil_client._ACTUATORS.pack(123456789, 1, *controls, mode)
    full = struct.Struct("<QQ16fB").pack(123456789, 1, *controls, *[0.0] * 12, mode)
    assert short == full
    encoder = mavlink.FrameEncoder(5, 1)
    cls = mav.MAVLink_hil_actuator_controls_message
    assert encoder.frame(cls.id, cls.crc_extra, short) == _pymavlink_frame(
        cls, dict(time_usec=123456789, controls=controls + [0.0] * 12, mode=mode, flags=1), 0, 5, 1)
