"""HIL_SENSOR as the simulator's link sends it, framed in one compiled call.

The ranges PX4 can take (accel and gyro: the sensor suite's limits of PX4's int16 storage;
magnetometer, baro) and `sensor_frame`, the kernel that clamps a step's IMU / magnetometer /
baro values into them, sets the `fields_updated` groups (`mavlink_kernels.FIELDS_*`) and frames
the message (MAVLink 2, `mavlink_kernels.write_frame`) into the link's buffer.
"""

from __future__ import annotations

import numpy as np

from sitl_bridge import mavlink_kernels
from sitl_bridge.jit import dual, kernel
from sitl_bridge.mavlink_kernels import (
    FIELDS_BARO,
    FIELDS_IMU,
    FIELDS_MAG,
    SENSOR_CRC,
    SENSOR_ID,
    SENSOR_LEN,
    write_frame,
)
from sitl_bridge.sensors import suite
from sitl_bridge.sensors.suite import ACCEL_LIMIT_M_S2, GYRO_LIMIT_RAD_S  # PX4's int16 ranges

MAG_LIMIT_GAUSS = 16.0
PRESSURE_RANGE_HPA = (1.0, 1200.0)
TEMPERATURE_RANGE_C = (-60.0, 85.0)
PRESSURE_ALT_RANGE_M = (-1000.0, 50000.0)


@dual
def clamp(value: float, low: float, high: float) -> float:
    """`value` limited to [low, high]; NaN -> 0 (PX4 would propagate it into its estimator)."""
    if value != value:
        return 0.0
    return low if value < low else high if value > high else value


@kernel(mavlink_kernels, suite)
def sensor_frame(
    out: np.ndarray,
    scratch: np.ndarray,
    sequence: int,
    system_id: int,
    component_id: int,
    wire_us: int,
    ax: float,
    ay: float,
    az: float,
    gx: float,
    gy: float,
    gz: float,
    has_mag: bool,
    mx: float,
    my: float,
    mz: float,
    has_baro: bool,
    pressure_hpa: float,
    temperature_c: float,
    pressure_alt_m: float,
) -> int:
    """The HIL_SENSOR frame (primary sensor, id 0) of one step into `out`; its length. Values
    out of PX4's ranges are clamped; mag and baro count (fields_updated) only when given."""
    a, g, m = ACCEL_LIMIT_M_S2, GYRO_LIMIT_RAD_S, MAG_LIMIT_GAUSS
    scratch[:] = 0
    f = scratch.view(np.float32)
    f[2], f[3], f[4] = clamp(ax, -a, a), clamp(ay, -a, a), clamp(az, -a, a)
    f[5], f[6], f[7] = clamp(gx, -g, g), clamp(gy, -g, g), clamp(gz, -g, g)
    fields = FIELDS_IMU
    if has_mag:
        f[8], f[9], f[10] = clamp(mx, -m, m), clamp(my, -m, m), clamp(mz, -m, m)
        fields |= FIELDS_MAG
    if has_baro:
        f[11] = clamp(pressure_hpa, PRESSURE_RANGE_HPA[0], PRESSURE_RANGE_HPA[1])
        f[13] = clamp(pressure_alt_m, PRESSURE_ALT_RANGE_M[0], PRESSURE_ALT_RANGE_M[1])
        f[14] = clamp(temperature_c, TEMPERATURE_RANGE_C[0], TEMPERATURE_RANGE_C[1])
        fields |= FIELDS_BARO
    scratch.view(np.int64)[0] = wire_us
    scratch.view(np.uint32)[15] = fields  # then id 0 (byte 64)
    return write_frame(
        out, 0, scratch, SENSOR_LEN, sequence, system_id, component_id, SENSOR_ID, SENSOR_CRC
    )
