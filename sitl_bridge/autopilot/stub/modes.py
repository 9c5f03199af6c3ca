"""PX4 flight modes (shared: `sitl_bridge.autopilot.modes`), landed states and command results
as MAVLink carries them."""

from __future__ import annotations

from enum import IntEnum

from sitl_bridge.autopilot.modes import (  # noqa: F401 - the stub's modes are PX4's
    HOLD,
    LAND,
    OFFBOARD,
    RTL,
    TAKEOFF,
    AutoSubMode,
    MainMode,
    custom_mode,
    mode_name,
    split_custom_mode,
)


class LandedState(IntEnum):
    """MAV_LANDED_STATE as sent in EXTENDED_SYS_STATE."""

    UNDEFINED = 0
    ON_GROUND = 1
    IN_AIR = 2
    TAKEOFF = 3
    LANDING = 4


class CommandResult(IntEnum):
    """MAV_RESULT: what a commander method answers, sent as COMMAND_ACK.result."""

    ACCEPTED = 0
    TEMPORARILY_REJECTED = 1
    DENIED = 2
    UNSUPPORTED = 3
    FAILED = 4


def system_id_for(instance: int) -> int:
    """MAVLink system id of vehicle instance i: 1 + i like PX4 (MAV_SYS_ID), wrapped into
    1..254 because the id is one byte (test instances go up to 2000)."""
    return 1 + instance % 254
