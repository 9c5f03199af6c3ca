"""`external`: autopilots this session does not start (`sitl-bridge stub -i N` or a PX4 started
by hand), which connect to TCP 4560+i the way PX4 connects to Gazebo."""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

from sitl_bridge.autopilot.fleet import (
    AutopilotFleet,
    Pump,
    SessionError,
    VehicleSummary,
    link_summary,
)

if TYPE_CHECKING:
    from sitl_bridge.hil import HilLink, Lockstep

log = logging.getLogger(__name__)


class ExternalFleet(AutopilotFleet):
    """Only waits for the autopilots to connect; it cannot reboot them with the simulation."""

    owns_autopilots = False

    def start(self, links: Sequence[HilLink]) -> list[Pump]:
        return []

    def connect(self, links: Sequence[HilLink], pumps: Sequence[Pump] = ()) -> None:
        super().connect(links, pumps)
        for link in links:
            log.info("vehicle %d: autopilot connected from %s", link.instance, link.peer)

    def close(self) -> None:
        pass

    def restart(self, lockstep: Lockstep, reset_simulation: Callable[[], None] | None = None) -> None:
        raise SessionError("reset: the autopilots are external (not started by this session), so "
                           "they cannot be rebooted with the simulation; restart them and the session")

    def summary(self, vehicle: int, link: HilLink) -> VehicleSummary:
        return link_summary(link)

    def describe(self) -> str:
        return ("waiting for autopilots to connect on the HIL ports (e.g. `sitl-bridge stub -i N`, "
                "or PX4 SITL started with PX4_SIM_MODEL=gazebo-classic_iris)")


__all__ = ["ExternalFleet"]
