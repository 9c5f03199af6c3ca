"""The ports of vehicle instance i: the one place they are written down.

PX4 SITL's scheme, which the simulator, the stub, the clients, the benchmarks and the tests
all follow (every service binds 127.0.0.1 by default):

| link | who listens / binds | port |
|---|---|---|
| HIL (simulator protocol, TCP) | the simulator listens, the autopilot connects | 4560+i |
| MAVLink API (offboard, UDP) | the autopilot binds, sends to the client | 14580+i -> 14540+i |
| GCS link (UDP) | the autopilot binds, sends to QGroundControl | 18570+i -> 14550 |

PX4's quirk: its `px4-rc.mavlink` sends the API link of every instance above 9 to UDP 14549
(`api_client_port(i, px4=True)`), so several real PX4 vehicles need instances 0..9.
"""

from __future__ import annotations

import socket
from dataclasses import dataclass

HIL_BASE_PORT = 4560
"""TCP 4560+i: the simulator's HIL server for vehicle i (PX4's `simulator_mavlink -c`)."""
API_BIND_BASE_PORT = 14580
"""UDP 14580+i: the autopilot's end of the MAVLink API link."""
API_CLIENT_BASE_PORT = 14540
"""UDP 14540+i: where the API link sends; MAVSDK listens here (`udpin://127.0.0.1:14540+i`)."""
GCS_BIND_BASE_PORT = 18570
"""UDP 18570+i: the autopilot's end of the GCS link."""
GCS_REMOTE_PORT = 14550
"""UDP 14550: where every vehicle's GCS link sends (QGroundControl listens here)."""
PX4_LAST_OWN_API_INSTANCE = 9
"""Real PX4 sends the API link of instances above this one to `PX4_SHARED_API_PORT`."""
PX4_SHARED_API_PORT = API_CLIENT_BASE_PORT + PX4_LAST_OWN_API_INSTANCE
"""UDP 14549: real PX4's API client port for every instance above 9 (px4-rc.mavlink)."""


def hil_port(instance: int) -> int:
    """TCP port of vehicle `instance`'s HIL link."""
    return HIL_BASE_PORT + instance


def api_bind_port(instance: int) -> int:
    """UDP port the autopilot of vehicle `instance` binds its MAVLink API link to."""
    return API_BIND_BASE_PORT + instance


def api_client_port(instance: int, *, px4: bool = False) -> int:
    """UDP port a MAVSDK client listens on for vehicle `instance`: 14540+i; with real PX4
    (`px4=True`) 14549 for every instance above 9."""
    if px4 and instance > PX4_LAST_OWN_API_INSTANCE:
        return PX4_SHARED_API_PORT
    return API_CLIENT_BASE_PORT + instance


def gcs_bind_port(instance: int) -> int:
    """UDP port the autopilot of vehicle `instance` binds its GCS link to."""
    return GCS_BIND_BASE_PORT + instance


@dataclass(frozen=True)
class VehiclePorts:
    """Every port of one vehicle instance (what `sitl-bridge run` prints)."""

    instance: int
    hil: int
    api_bind: int
    api_client: int
    gcs_bind: int
    gcs_remote: int = GCS_REMOTE_PORT

    def describe(self, host: str = "127.0.0.1") -> str:
        """One line: HIL, MAVSDK URL, API and GCS ports."""
        return (f"HIL tcp://{host}:{self.hil}, MAVSDK udpin://{host}:{self.api_client} "
                f"(API from udp {self.api_bind}), GCS udp {self.gcs_bind} -> {self.gcs_remote}")


def vehicle_ports(instance: int, *, px4: bool = False) -> VehiclePorts:
    """The ports of vehicle `instance` (`px4`: with real PX4's API port quirk)."""
    return VehiclePorts(instance, hil_port(instance), api_bind_port(instance),
                        api_client_port(instance, px4=px4), gcs_bind_port(instance))


def instance_sockets(instance: int) -> tuple[tuple[int, int], ...]:
    """(port, socket type) of everything vehicle `instance` binds or listens on, for
    "is this instance free?" checks (tests, benchmarks)."""
    return ((hil_port(instance), socket.SOCK_STREAM), (api_bind_port(instance), socket.SOCK_DGRAM),
            (api_client_port(instance), socket.SOCK_DGRAM), (gcs_bind_port(instance), socket.SOCK_DGRAM))


def instance_free(instance: int, host: str = "127.0.0.1") -> bool:
    """True when every port of vehicle `instance` can be bound on `host` now. A TCP port in
    TIME_WAIT counts as free (our servers set SO_REUSEADDR too)."""
    for port, kind in instance_sockets(instance):
        with socket.socket(socket.AF_INET, kind) as sock:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                sock.bind((host, port))
            except OSError:
                return False
    return True


MAX_INSTANCE = 253
"""Highest vehicle instance: MAVLink system id 1 + i must fit in a byte."""

__all__ = [
    "API_BIND_BASE_PORT", "API_CLIENT_BASE_PORT", "GCS_BIND_BASE_PORT", "GCS_REMOTE_PORT",
    "HIL_BASE_PORT", "MAX_INSTANCE", "PX4_LAST_OWN_API_INSTANCE", "PX4_SHARED_API_PORT", "VehiclePorts",
    "api_bind_port", "api_client_port", "gcs_bind_port", "hil_port", "instance_free",
    "instance_sockets", "vehicle_ports",
]
