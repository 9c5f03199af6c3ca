"""PX4 flight modes as MAVLink carries them (HEARTBEAT.custom_mode), and their names.

The one place for them: the stub's commander flies these modes, and the session's status
line names what any PX4-like autopilot reports (stub or real PX4).
"""

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
    RTGS = 7
    FOLLOW_TARGET = 8
    PRECLAND = 9


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

MAIN_MODE_NAMES = {
    MainMode.MANUAL: "Manual", MainMode.ALTCTL: "Altitude", MainMode.POSCTL: "Position",
    MainMode.AUTO: "Auto", MainMode.ACRO: "Acro", MainMode.OFFBOARD: "Offboard",
    MainMode.STABILIZED: "Stabilized", MainMode.RATTITUDE: "Rattitude",
}
"""Names QGroundControl shows for the main modes."""
AUTO_SUB_MODE_NAMES = {
    AutoSubMode.READY: "Ready", AutoSubMode.TAKEOFF: "Takeoff", AutoSubMode.LOITER: "Hold",
    AutoSubMode.MISSION: "Mission", AutoSubMode.RTL: "Return", AutoSubMode.LAND: "Land",
    AutoSubMode.RTGS: "ReturnToGroundStation", AutoSubMode.FOLLOW_TARGET: "FollowTarget",
    AutoSubMode.PRECLAND: "Precland",
}
"""Names QGroundControl shows for the AUTO sub-modes."""


def mode_name(value: int) -> str:
    """PX4 flight mode name of a HEARTBEAT custom_mode, as QGroundControl shows it."""
    main, sub = split_custom_mode(value)
    if main == MainMode.AUTO:
        return AUTO_SUB_MODE_NAMES.get(sub, f"Auto({sub})")  # type: ignore[call-overload]
    return MAIN_MODE_NAMES.get(main, f"mode {value}")  # type: ignore[call-overload]


__all__ = [
    "AUTO_SUB_MODE_NAMES", "HOLD", "LAND", "MAIN_MODE_NAMES", "OFFBOARD", "RTL", "TAKEOFF",
    "AutoSubMode", "MainMode", "custom_mode", "mode_name", "split_custom_mode",
]
