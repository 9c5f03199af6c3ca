"""MAVSDK side: `OffboardClient` (one vehicle), `Fleet` (several, one clock), thesis actions."""

from sitl_bridge.client.actions import (
    ACTION_DURATION_S,
    ACTION_SPEED_M_S,
    NUM_ACTIONS,
    Action,
    action_velocity_ned,
)
from sitl_bridge.client.fleet import Fleet
from sitl_bridge.client.offboard import (
    OffboardClient,
    OffboardClientError,
    SimClock,
    SimTimeoutError,
    VehicleStatus,
    wait_until,
)

__all__ = [
    "ACTION_DURATION_S",
    "ACTION_SPEED_M_S",
    "NUM_ACTIONS",
    "Action",
    "Fleet",
    "OffboardClient",
    "OffboardClientError",
    "SimClock",
    "SimTimeoutError",
    "VehicleStatus",
    "action_velocity_ned",
    "wait_until",
]
