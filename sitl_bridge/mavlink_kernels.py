"""Compiled MAVLink 2 framing for the per-step simulator messages (numba, `sitl_bridge.jit`).

`mavlink.FrameParser` / `FrameEncoder` frame any message in Python; these helpers check, decode
and frame the lockstep's own messages inside kernels (the stub's `hil_fused`, the simulator's
`HilLink` read of HIL_ACTUATOR_CONTROLS): the same frames, checksum and zero-extension rules,
without a frame object per message. Their tests hold them to the Python codec.
"""

from __future__ import annotations

import math

import numpy as np

from sitl_bridge import mavlink
from sitl_bridge.jit import dual, kernel

d = mavlink.dialect
# ids, CRC_EXTRA and full payload lengths of the three messages (literals: compiled in)
SENSOR_ID, SENSOR_CRC, SENSOR_LEN = 107, 108, 65
GPS_ID, GPS_CRC, GPS_LEN = 113, 124, 39
ACT_ID, ACT_CRC, ACT_LEN = 93, 47, 81
for _cls, (_id, _crc, _len) in (
    (d.MAVLink_hil_sensor_message, (SENSOR_ID, SENSOR_CRC, SENSOR_LEN)),
    (d.MAVLink_hil_gps_message, (GPS_ID, GPS_CRC, GPS_LEN)),
    (d.MAVLink_hil_actuator_controls_message, (ACT_ID, ACT_CRC, ACT_LEN)),
):
    if (_cls.id, _cls.crc_extra, _cls.unpacker.size) != (_id, _crc, _len):  # pragma: no cover
        raise ImportError(f"pymavlink's {_cls.__name__} differs from the compiled-in layout")
# HIL_SENSOR fields_updated groups: PX4 reads a group only when all its bits are set
# (SimulatorMavlink.hpp SensorSource).
FIELDS_ACCEL = 0x0007
FIELDS_GYRO = 0x0038
FIELDS_MAG = 0x01C0
FIELDS_BARO = 0x1A00  # abs_pressure, pressure_alt, temperature
FIELDS_IMU = FIELDS_ACCEL | FIELDS_GYRO
HEADER = mavlink.MAVLINK2_HEADER_LEN
SCRATCH_BYTES = 96  # payload scratch (a multiple of 8, >= every payload)


@dual
def crc_add(crc: int, byte: int) -> int:
    """MAVLink's CRC-16/MCRF4XX (`mavlink.crc_mcrf4xx`) advanced by one byte."""
    tmp = (byte ^ crc) & 0xFF
    tmp = (tmp ^ (tmp << 4)) & 0xFF
    return ((crc >> 8) ^ (tmp << 8) ^ (tmp << 3) ^ (tmp >> 4)) & 0xFFFF


@dual
def frame_crc(buf, start: int, end: int, crc_extra: int) -> int:  # noqa: ANN001
    """The MAVLink checksum of a frame whose header and payload after the magic byte are
    buf[start:end] (then CRC_EXTRA)."""
    crc = 0xFFFF
    for i in range(start, end):
        crc = crc_add(crc, buf[i])
    return crc_add(crc, crc_extra)


@dual
def float32_value(bits: int) -> float:
    """The float32 with these bits, as float64, from the bits (exact). Not a float32 -> float64
    cast: in a kernel, LLVM may then evaluate expressions of the value in float32 (a sqrt of a
    sum of squares, say), and the estimator would not be the one `direct` and Python call."""
    exponent = (bits >> 23) & 0xFF
    mantissa = bits & 0x7FFFFF
    if exponent == 0xFF:
        value = math.inf if mantissa == 0 else math.nan
    elif exponent == 0:
        value = math.ldexp(float(mantissa), -149)
    else:
        value = math.ldexp(float(mantissa | 0x800000), exponent - 150)
    return -value if bits >> 31 else value


@dual
def checked_frame(
    data, pos: int, msgid: int, crc_extra: int, full: int, scratch: np.ndarray
) -> int:  # noqa: ANN001
    """The end of the unsigned MAVLink 2 frame `msgid` at `pos` with a good checksum, its payload
    zero-extended into `scratch`; -1 when there is no such frame."""
    n = len(data)
    if n - pos < HEADER + 2 or data[pos] != 0xFD or data[pos + 2] != 0:
        return -1
    length = data[pos + 1]
    end = pos + HEADER + length + 2
    if (
        end > n
        or length > full
        or (data[pos + 7] | (data[pos + 8] << 8) | (data[pos + 9] << 16)) != msgid
    ):
        return -1
    crc = frame_crc(data, pos + 1, pos + HEADER + length, crc_extra)
    if crc != data[end - 2] | (data[end - 1] << 8):
        return -1
    scratch[:] = 0
    for i in range(length):
        scratch[i] = data[pos + HEADER + i]
    return end


@dual
def write_frame(
    out: np.ndarray,
    pos: int,
    payload: np.ndarray,
    full: int,
    sequence: int,
    system_id: int,
    component_id: int,
    msgid: int,
    crc_extra: int,
) -> int:
    """Frame payload[:full] as unsigned MAVLink 2 at out[pos:] (trailing zeros truncated, as
    `mavlink.FrameEncoder.frame`); returns the frame's end."""
    length = full
    while length > 1 and payload[length - 1] == 0:
        length -= 1
    out[pos], out[pos + 1], out[pos + 2], out[pos + 3], out[pos + 4] = 0xFD, length, 0, 0, sequence
    out[pos + 5], out[pos + 6] = system_id, component_id
    out[pos + 7], out[pos + 8], out[pos + 9] = msgid & 0xFF, (msgid >> 8) & 0xFF, msgid >> 16
    for i in range(length):
        out[pos + HEADER + i] = payload[i]
    end = pos + HEADER + length
    crc = frame_crc(out, pos + 1, end, crc_extra)
    out[end], out[end + 1] = crc & 0xFF, crc >> 8
    return end + 2


@kernel()
def actuator_values(data: bytes, scratch: np.ndarray) -> tuple:
    """(1, time_usec, flags, mode, controls 1..4) when `data` is exactly one checked
    HIL_ACTUATOR_CONTROLS frame (controls 5..16 are not read), else (0, ...)."""
    if checked_frame(data, 0, ACT_ID, ACT_CRC, ACT_LEN, scratch) != len(data):
        return 0, 0, 0, 0, 0.0, 0.0, 0.0, 0.0
    u, w = scratch.view(np.uint32), scratch.view(np.int64)
    return (
        1,
        w[0],
        w[1],
        scratch[ACT_LEN - 1],
        float32_value(u[4]),
        float32_value(u[5]),
        float32_value(u[6]),
        float32_value(u[7]),
    )
