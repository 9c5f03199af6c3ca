"""Where the stub lets a position command (DO_REPOSITION) send its vehicle.

Every stub refuses a target farther than `REACH_M` from its local origin along any axis (an
altitude of 1e30 m, a point in another country). A stub that knows its world (`Fence`, given
by the session's fleets: the in-process `stub` and, through `sitl-bridge stub --fence`, the
`stub-process` kind) also refuses targets outside the world's workspace box: the envs end an
episode there, and PX4 would refuse a reposition outside its geofence. A refusal is a
COMMAND_ACK DENIED with a STATUSTEXT saying why.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from sitl_bridge.errors import ConfigError
from sitl_bridge.sensors.geodesy import Projection
from sitl_bridge.world.schema import GeoHome, World

REACH_M = 20_000.0
"""The farthest a stub flies from its local origin, per axis (no Iris battery goes further)."""


@dataclass(frozen=True)
class Fence:
    """A world's workspace box (ENU metres around `home`, the world's geodetic origin)."""

    home: GeoHome
    min_enu_m: tuple[float, float, float]
    max_enu_m: tuple[float, float, float]

    @classmethod
    def of_world(cls, world: World) -> Fence:
        return cls(world.home, tuple(world.workspace.min_m), tuple(world.workspace.max_m))  # type: ignore[arg-type]

    def to_text(self) -> str:
        """`lat,lon,alt,min_x,min_y,min_z,max_x,max_y,max_z` (what `from_text` reads)."""
        h = self.home
        return ",".join(repr(float(v)) for v in (h.lat_deg, h.lon_deg, h.alt_m, *self.min_enu_m, *self.max_enu_m))

    @classmethod
    def from_text(cls, text: str) -> Fence:
        """The fence `to_text` wrote; a one-line ConfigError for anything else."""
        try:
            values = [float(part) for part in text.split(",")]
        except ValueError:
            values = []
        if len(values) != 9 or not all(math.isfinite(v) for v in values) or \
                any(lo > hi for lo, hi in zip(values[3:6], values[6:9], strict=True)):
            raise ConfigError(f"--fence: expected lat,lon,alt,min_x,min_y,min_z,max_x,max_y,max_z "
                              f"(finite, min <= max), got {text[:80]!r}")
        return cls(GeoHome(values[0], values[1], values[2]), tuple(values[3:6]), tuple(values[6:9]))  # type: ignore[arg-type]

    def outside(self, lat_deg: float, lon_deg: float, alt_amsl_m: float) -> bool:
        """Whether a global position lies outside the workspace box."""
        north, east, down = Projection(self.home).to_local(lat_deg, lon_deg, alt_amsl_m)
        enu = (east, north, -down)
        return not all(lo <= x <= hi for x, lo, hi in zip(enu, self.min_enu_m, self.max_enu_m, strict=True))
