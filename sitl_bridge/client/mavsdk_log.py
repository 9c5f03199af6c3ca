"""Send MAVSDK's C++ log lines to Python logging (logger `mavsdk`) instead of stdout."""

from __future__ import annotations

import logging

from mavsdk import LogLevel, log_subscribe

_logger = logging.getLogger("mavsdk")
_LEVELS = {
    LogLevel.DEBUG: logging.DEBUG,
    LogLevel.INFO: logging.DEBUG,  # MAVSDK's info lines (version, new system) are chatter for us
    LogLevel.WARN: logging.WARNING,
    LogLevel.ERROR: logging.ERROR,
}
_installed = False


def _forward(level: LogLevel, message: str, file: str | None, line: int) -> bool:
    _logger.log(_LEVELS.get(level, logging.INFO), "%s", message)
    return True  # True: MAVSDK does not print it itself


def route_mavsdk_logs() -> None:
    """Install the forwarder once per process (MAVSDK's log hook is global)."""
    global _installed
    if not _installed:
        log_subscribe(_forward)
        _installed = True
