"""The built-in PX4-compatible autopilot stub.

- `StubAutopilot` (autopilot.py): estimator + commander + PX4-style control cascade + mixer,
  one `update(SensorFrame) -> MotorCommand` per lockstep step, no I/O.
- `MavlinkApi` (mavlink_api.py): PX4's MAVLink API on UDP for MAVSDK / QGC.
- `HilClient` (hil_client.py): the PX4 side of the simulator TCP link.
- `StubVehicle` (vehicle.py): the three together, per vehicle instance.
"""

from .autopilot import StubAutopilot
from .hil_client import HilClient
from .mavlink_api import MavlinkApi
from .modes import AutoSubMode, CommandResult, LandedState, MainMode, custom_mode
from .params import ParamTable
from .vehicle import StubVehicle

__all__ = [
    "AutoSubMode", "CommandResult", "HilClient", "LandedState", "MainMode", "MavlinkApi", "ParamTable",
    "StubAutopilot", "StubVehicle", "custom_mode",
]
