"""Sensors: IMU, magnetometer, barometer, GPS and ground truth (`SensorSuite` -> `SensorFrame`),
lidar (`Lidar` -> `LidarScan`), and the geodesy / atmosphere / magnetic field they measure."""

from sitl_bridge.sensors.geodesy import Projection, geodetic_to_local_ned, local_ned_to_geodetic
from sitl_bridge.sensors.lidar import Lidar, LidarConfig, LidarScan
from sitl_bridge.sensors.seeding import sensor_seed
from sitl_bridge.sensors.suite import (
    BaroSample,
    GpsSample,
    GroundTruth,
    SensorFrame,
    SensorNoise,
    SensorRates,
    SensorSuite,
)

__all__ = [
    "BaroSample", "GpsSample", "GroundTruth", "Lidar", "LidarConfig", "LidarScan", "Projection", "SensorFrame", "SensorNoise", "SensorRates",
    "SensorSuite", "geodetic_to_local_ned", "local_ned_to_geodetic", "sensor_seed",
]
