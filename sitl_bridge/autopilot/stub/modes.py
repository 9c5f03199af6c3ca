"""PX4 flight modes, landed states and command results as MAVLink carries them."""

from __future__ import annotations

from enum import IntEnum


class MainMode(IntEnum):
    """PX4 main modes (custom_mode bits 16-23)."""

    MANUAL = 1
    ALTCTL = 2
    POSCTL = 3
    AUTO = 4
    ACRO = 5
    OFFBOARD = 6
    STABILIZED = 7
    RATTITUDE = 8


class AutoSubMode(IntEnum):
    """PX4 AUTO sub-modes (custom_mode bits 24-31)."""

    READY = 1
    TAKEOFF = 2
    LOITER = 3
    MISSION = 4
    RTL = 5
    LAND = 6


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


def custom_mode(main_mode: int, sub_mode: int = 0) -> int:
    """PX4's HEARTBEAT.custom_mode: main mode in bits 16-23, sub mode in bits 24-31."""
    return ((int(main_mode) & 0xFF) << 16) | ((int(sub_mode) & 0xFF) << 24)


def split_custom_mode(value: int) -> tuple[int, int]:
    """(main_mode, sub_mode) of a PX4 custom_mode."""
    return (value >> 16) & 0xFF, (value >> 24) & 0xFF


HOLD = (MainMode.AUTO, AutoSubMode.LOITER)
TAKEOFF = (MainMode.AUTO, AutoSubMode.TAKEOFF)
LAND = (MainMode.AUTO, AutoSubMode.LAND)
RTL = (MainMode.AUTO, AutoSubMode.RTL)
OFFBOARD = (MainMode.OFFBOARD, 0)


def system_id_for(instance: int) -> int:
    """MAVLink system id of vehicle instance i: 1 + i like PX4 (MAV_SYS_ID), wrapped into
    1..254 because the id is one byte (test instances go up to 2000)."""
    return 1 + instance % 254
