"""The one place that imports pymavlink, plus fast MAVLink 2 framing for the hot paths.

pymavlink picks its dialect from the environment at import time; importing the MAVLink 2
`common` dialect module directly pins MAVLink 2 for the whole package. Everything else imports
`dialect` (messages, enums, CRCs) and `new_codec` from here.

The simulator link sends three messages and receives one per 4 ms step and vehicle, so it
does not go through pymavlink's per-message objects: `FrameEncoder` packs a payload with the
message's precompiled `struct` and frames it (MAVLink 2, trailing-zero truncation, CRC with
the message's CRC_EXTRA); `FrameParser` splits a TCP byte stream into checked frames, counting
garbage bytes and CRC failures instead of raising. Rare messages are still decoded by
pymavlink (`decode_frame`).
"""

from __future__ import annotations

import binascii
import dataclasses
import os
import re
import struct
from dataclasses import dataclass
from typing import NamedTuple

os.environ.setdefault("MAVLINK20", "1")

from pymavlink.dialects.v20 import common as dialect  # noqa: E402
from pymavlink.generator import mavcrc  # noqa: E402

MAVLink = dialect.MAVLink
MAVLinkMessage = dialect.MAVLink_message

MAVLINK2_MAGIC = 0xFD
MAVLINK1_MAGIC = 0xFE
MAVLINK2_HEADER_LEN = 10
MAVLINK1_HEADER_LEN = 6
MAVLINK_IFLAG_SIGNED = 0x01
MAVLINK_SIGNATURE_LEN = 13
_HEADER2 = struct.Struct("<BBBBBBBHB")  # magic len incompat compat seq sys comp msgid(24 bit)
_HEADER1 = struct.Struct("<BBBBBB")  # magic len seq sys comp msgid
_CRC_EXTRA_BYTES = [bytes((i,)) for i in range(256)]

# Message ids used by the simulator protocol (PX4 SimulatorMavlink).
HEARTBEAT = dialect.MAVLINK_MSG_ID_HEARTBEAT
COMMAND_LONG = dialect.MAVLINK_MSG_ID_COMMAND_LONG
HIL_ACTUATOR_CONTROLS = dialect.MAVLINK_MSG_ID_HIL_ACTUATOR_CONTROLS
HIL_SENSOR = dialect.MAVLINK_MSG_ID_HIL_SENSOR
HIL_GPS = dialect.MAVLINK_MSG_ID_HIL_GPS
HIL_STATE_QUATERNION = dialect.MAVLINK_MSG_ID_HIL_STATE_QUATERNION
MAV_CMD_SET_MESSAGE_INTERVAL = dialect.MAV_CMD_SET_MESSAGE_INTERVAL
MAV_MODE_FLAG_SAFETY_ARMED = dialect.MAV_MODE_FLAG_SAFETY_ARMED


class _NullFile:
    """pymavlink's codec wants a file to write to; we send the bytes ourselves."""

    def write(self, data: bytes) -> None:  # pragma: no cover - never used for output
        pass


def new_codec(system_id: int, component_id: int) -> dialect.MAVLink:
    """A MAVLink 2 encoder/decoder with the given sender ids, robust to garbage bytes."""
    codec = dialect.MAVLink(_NullFile(), srcSystem=system_id, srcComponent=component_id)
    codec.robust_parsing = True
    return codec


# -- CRC-16/MCRF4XX (MAVLink's "x25") ---------------------------------------------------------
_BIT_REVERSED = bytes(int(f"{i:08b}"[::-1], 2) for i in range(256))


def _crc_binascii(data: bytes, crc: int = 0xFFFF) -> int:
    """MCRF4XX is the bit-reflected CCITT CRC: reflect the input bytes, run binascii's
    (C) CCITT CRC, reflect the result. Used when pymavlink has no native CRC."""
    crc = (_BIT_REVERSED[crc & 0xFF] << 8) | _BIT_REVERSED[crc >> 8]
    out = binascii.crc_hqx(bytes(data).translate(_BIT_REVERSED), crc)
    return (_BIT_REVERSED[out & 0xFF] << 8) | _BIT_REVERSED[out >> 8]


crc_mcrf4xx = mavcrc.mcrf4xx if getattr(mavcrc, "mcrf4xx", None) else _crc_binascii
"""crc_mcrf4xx(data, crc=0xFFFF) -> int: the MAVLink checksum (native when available)."""


def message_class(msgid: int) -> type[MAVLinkMessage] | None:
    """The dialect's message class for `msgid`, or None when the dialect does not know it."""
    return dialect.mavlink_map.get(msgid)


# -- encoding ---------------------------------------------------------------------------------
class FrameEncoder:
    """Packs MAVLink 2 frames for one sender (system id, component id, sequence counter).

    `pack(message_class, *wire_values)` takes the payload values in wire order (the order of
    `message_class.ordered_fieldnames`, arrays flattened), exactly as the message's struct
    wants them. About 4x faster than building pymavlink message objects.
    """

    def __init__(self, system_id: int, component_id: int) -> None:
        self.system_id = system_id
        self.component_id = component_id
        self.sequence = 0

    def pack(self, message_class: type[MAVLinkMessage], *wire_values: float | int) -> bytes:
        """One complete MAVLink 2 frame carrying `wire_values`."""
        return self.frame(message_class.id, message_class.crc_extra, message_class.unpacker.pack(*wire_values))

    def take_sequence(self) -> int:
        """The sequence number of the next frame, counted as sent (frames built elsewhere, e.g.
        in a compiled kernel, take theirs here so the counter stays one per link)."""
        sequence = self.sequence
        self.sequence = (sequence + 1) & 0xFF
        return sequence

    def frame(self, msgid: int, crc_extra: int, payload: bytes) -> bytes:
        """Frame an already packed payload (trailing zero bytes are truncated, as MAVLink 2
        senders do; receivers zero-extend)."""
        payload = payload.rstrip(b"\0") or b"\0"
        sequence = self.take_sequence()
        # everything after the magic byte, which is what the checksum covers (then CRC_EXTRA)
        body = _HEADER2_AFTER_MAGIC.pack(len(payload), 0, 0, sequence, self.system_id, self.component_id,
                                         msgid & 0xFFFF, msgid >> 16) + payload
        return _MAGIC2_BYTE + body + _CRC_BYTES(crc_mcrf4xx(body + _CRC_EXTRA_BYTES[crc_extra]))


_HEADER2_AFTER_MAGIC = struct.Struct("<BBBBBBHB")  # _HEADER2 without its first byte
_MAGIC2_BYTE = bytes((MAVLINK2_MAGIC,))
_CRC_BYTES = struct.Struct("<H").pack


# -- decoding ---------------------------------------------------------------------------------
class Frame(NamedTuple):
    """One checked MAVLink frame. `payload` is zero-extended to the dialect's full length
    (truncated v2 payloads) or cut to it (a newer dialect's extra extensions)."""

    msgid: int
    system_id: int
    component_id: int
    sequence: int
    payload: bytes
    raw: bytes


@dataclass
class ParserStats:
    """What the parser threw away, for logs and tests."""

    frames: int = 0
    garbage_bytes: int = 0
    bad_crc: int = 0
    unknown_msgid: int = 0


_MAGIC = re.compile(b"[\xfd\xfe]")


_INCOMPLETE = -1
_BAD = 0


class FrameParser:
    """Splits a byte stream (TCP, partial reads) into CRC-checked MAVLink 1/2 frames.

    Never raises on bad input: bytes before a frame start, frames with a bad checksum and
    frames with ids the dialect does not know are skipped and counted in `stats`. A fake
    header in garbage (a magic byte followed by a long length) does not stall the stream: when
    a complete, valid frame starts after it, the fake header is skipped without waiting for
    the bytes it claims.
    """

    # Cap on buffered bytes, so a peer that sends only garbage cannot grow memory.
    MAX_BUFFER = 1 << 20

    def __init__(self) -> None:
        self._buffer = bytearray()
        self.stats = ParserStats()

    @property
    def holds_partial(self) -> bool:
        """Bytes of an incomplete frame are waiting for the next `feed` (a new read does not
        start on a frame boundary)."""
        return bool(self._buffer)

    def feed(self, data: bytes) -> list[Frame]:
        """Add received bytes; return the complete frames now available, in order."""
        buf = self._buffer
        if not buf and type(data) is bytes:
            # the usual case: whole unsigned MAVLink 2 frames of known ids (one step's messages)
            frames, pos = _whole_v2_frames(data)
            self.stats.frames += len(frames)
            if pos == len(data):
                return frames
            # anything else (garbage, a split frame, MAVLink 1, signing) from there on: the full path
            return frames + self._feed(data[pos:])
        return self._feed(data)

    def _feed(self, data: bytes) -> list[Frame]:
        buf = self._buffer
        if buf:
            buf += data
            source: bytes | bytearray = buf
        else:
            # the usual case, whole frames per read: parse the received bytes in place (a
            # complete frame is then a slice of them, not a copy of a copy)
            source = data
        frames: list[Frame] = []
        pos = 0
        size = len(source)
        stats = self.stats
        while pos < size:
            magic = source[pos]
            if magic != MAVLINK2_MAGIC and magic != MAVLINK1_MAGIC:
                found = _MAGIC.search(source, pos)
                next_pos = found.start() if found else size
                stats.garbage_bytes += next_pos - pos
                pos = next_pos
                continue
            total = self._check(source, pos, size, frames)
            if total > 0:
                pos += total
                continue
            if total == _BAD:
                stats.garbage_bytes += 1
                pos += 1
                continue
            # Incomplete: a real frame still arriving, or a fake header. Only skip it when a
            # complete valid frame follows.
            later = self._find_complete(source, pos + 1, size, frames)
            if later is None:
                break
            stats.garbage_bytes += later[0] - pos
            pos = later[0] + later[1]
        if source is buf:
            del buf[:pos]
        elif pos < size:
            buf += source[pos:]  # the start of a frame still arriving
        if len(buf) > self.MAX_BUFFER:
            stats.garbage_bytes += len(buf)
            buf.clear()
        return frames

    def _find_complete(
        self, buf: bytearray, start: int, size: int, frames: list[Frame]
    ) -> tuple[int, int] | None:
        """(position, length) of the first complete valid frame at or after `start`."""
        stats = dataclasses.replace(self.stats)  # look-ahead failures are not counted
        for found in _MAGIC.finditer(buf, start):
            total = self._check(buf, found.start(), size, frames)
            if total > 0:
                self.stats.bad_crc, self.stats.unknown_msgid = stats.bad_crc, stats.unknown_msgid
                return found.start(), total
        self.stats.bad_crc, self.stats.unknown_msgid = stats.bad_crc, stats.unknown_msgid
        return None

    def _check(self, buf: bytes | bytearray, pos: int, size: int, frames: list[Frame]) -> int:
        """Frame at `pos`: appends it and returns its length, or _BAD / _INCOMPLETE."""
        if buf[pos] == MAVLINK2_MAGIC:
            if size - pos < MAVLINK2_HEADER_LEN:
                return _INCOMPLETE
            _, length, incompat, _, seq, sysid, compid, low, high = _HEADER2.unpack_from(buf, pos)
            msgid = low | (high << 16)
            total = MAVLINK2_HEADER_LEN + length + 2
            if incompat & MAVLINK_IFLAG_SIGNED:
                total += MAVLINK_SIGNATURE_LEN
            header_len = MAVLINK2_HEADER_LEN
        else:
            if size - pos < MAVLINK1_HEADER_LEN:
                return _INCOMPLETE
            _, length, seq, sysid, compid, msgid = _HEADER1.unpack_from(buf, pos)
            total = MAVLINK1_HEADER_LEN + length + 2
            header_len = MAVLINK1_HEADER_LEN
        info = _MESSAGE_INFO.get(msgid)
        if info is None:
            # Can't check the CRC without CRC_EXTRA: treat the magic byte as garbage and
            # resynchronise on the next one rather than trusting the length byte.
            self.stats.unknown_msgid += 1
            return _BAD
        if size - pos < total:
            return _INCOMPLETE
        crc_extra, full = info
        # bytes(...) of a bytes slice is the slice itself; of a bytearray, one copy
        raw = bytes(buf[pos : pos + total])
        end_payload = header_len + length
        crc = crc_mcrf4xx(crc_extra, crc_mcrf4xx(memoryview(raw)[1:end_payload]))
        if crc != raw[end_payload] | (raw[end_payload + 1] << 8):
            self.stats.bad_crc += 1
            return _BAD
        if length < full:
            payload = raw[header_len:end_payload] + _ZERO_PADDING[full - length]
        else:
            payload = raw[header_len : header_len + full]
        frames.append(_new_frame(Frame, (msgid, sysid, compid, seq, payload, raw)))
        self.stats.frames += 1
        return total


# msgid -> (CRC_EXTRA as a byte, full payload length), for the parser's per-frame checks
_MESSAGE_INFO: dict[int, tuple[bytes, int]] = {
    msgid: (_CRC_EXTRA_BYTES[cls.crc_extra], cls.unpacker.size) for msgid, cls in dialect.mavlink_map.items()
}
_ZERO_PADDING = [bytes(n) for n in range(256)]
# Frame(...) goes through a Python-level __new__; tuple.__new__ builds the same object directly
_new_frame = tuple.__new__


def _whole_v2_frames(data: bytes) -> tuple[list[Frame], int]:
    """The frames at the start of `data` that are complete, unsigned MAVLink 2 frames of known
    ids with a good checksum, and where the first byte not taken lies. The same frames as
    `FrameParser._check` gives, in fewer steps (this runs for every message of every step)."""
    frames: list[Frame] = []
    pos = 0
    size = len(data)
    while size - pos >= MAVLINK2_HEADER_LEN + 2 and data[pos] == MAVLINK2_MAGIC and not data[pos + 2]:
        length = data[pos + 1]
        end = pos + MAVLINK2_HEADER_LEN + length + 2
        if end > size:
            break
        msgid = data[pos + 7] | (data[pos + 8] << 8) | (data[pos + 9] << 16)
        info = _MESSAGE_INFO.get(msgid)
        if info is None:
            break
        raw = data if pos == 0 and end == size else data[pos:end]
        end_payload = MAVLINK2_HEADER_LEN + length
        if crc_mcrf4xx(info[0], crc_mcrf4xx(raw[1:end_payload])) != raw[end_payload] | (raw[end_payload + 1] << 8):
            break
        full = info[1]
        payload = raw[MAVLINK2_HEADER_LEN:end_payload] + _ZERO_PADDING[full - length] if length < full \
            else raw[MAVLINK2_HEADER_LEN:MAVLINK2_HEADER_LEN + full]
        frames.append(_new_frame(Frame, (msgid, raw[5], raw[6], raw[4], payload, raw)))
        pos = end
    return frames, pos


def unpack_payload(frame: Frame) -> tuple:
    """The frame's payload values in wire order (arrays flattened), via the dialect's struct."""
    return dialect.mavlink_map[frame.msgid].unpacker.unpack(frame.payload)


def decode_frame(codec: dialect.MAVLink, frame: Frame) -> MAVLinkMessage:
    """A pymavlink message object for a frame (for rare messages, tests and logs)."""
    return codec.decode(bytearray(frame.raw))
