"""Local NED <-> geodetic conversion exactly as Gazebo-classic's PX4 plugins do it.

Azimuthal equidistant projection around the home position on a sphere of radius 6 353 000 m
(`include/common.h`, `reproject`). Altitude is home altitude plus height above the origin.
"""

from __future__ import annotations

import math

from sitl_bridge.world.schema import GeoHome

EARTH_RADIUS_M = 6_353_000.0


class Projection:
    """Precomputed projection around one home position (cheap per-step calls)."""

    def __init__(self, home: GeoHome) -> None:
        self.home = home
        self._lat0 = math.radians(home.lat_deg)
        self._lon0 = math.radians(home.lon_deg)
        self._sin_lat0 = math.sin(self._lat0)
        self._cos_lat0 = math.cos(self._lat0)

    def to_geodetic(self, north_m: float, east_m: float, down_m: float) -> tuple[float, float, float]:
        """Local NED (m) -> (lat_deg, lon_deg, alt_m AMSL)."""
        x = north_m / EARTH_RADIUS_M
        y = east_m / EARTH_RADIUS_M
        c = math.sqrt(x * x + y * y)
        if c == 0.0:
            return self.home.lat_deg, self.home.lon_deg, self.home.alt_m - down_m
        sin_c, cos_c = math.sin(c), math.cos(c)
        lat = math.asin(cos_c * self._sin_lat0 + x * sin_c * self._cos_lat0 / c)
        lon = self._lon0 + math.atan2(y * sin_c, c * self._cos_lat0 * cos_c - x * self._sin_lat0 * sin_c)
        return math.degrees(lat), math.degrees(lon), self.home.alt_m - down_m

    def to_local(self, lat_deg: float, lon_deg: float, alt_m: float) -> tuple[float, float, float]:
        """(lat_deg, lon_deg, alt_m AMSL) -> local NED (m); the inverse of `to_geodetic`."""
        lat = math.radians(lat_deg)
        dlon = math.radians(lon_deg) - self._lon0
        sin_lat, cos_lat = math.sin(lat), math.cos(lat)
        cos_dlon = math.cos(dlon)
        arg = self._sin_lat0 * sin_lat + self._cos_lat0 * cos_lat * cos_dlon
        c = math.acos(max(-1.0, min(1.0, arg)))
        k = 1.0 if c == 0.0 else c / math.sin(c)
        north = k * (self._cos_lat0 * sin_lat - self._sin_lat0 * cos_lat * cos_dlon) * EARTH_RADIUS_M
        east = k * cos_lat * math.sin(dlon) * EARTH_RADIUS_M
        return north, east, self.home.alt_m - alt_m


def local_ned_to_geodetic(home: GeoHome, north_m: float, east_m: float, down_m: float) -> tuple[float, float, float]:
    """Local NED (m) around `home` -> (lat_deg, lon_deg, alt_m AMSL)."""
    return Projection(home).to_geodetic(north_m, east_m, down_m)


def geodetic_to_local_ned(home: GeoHome, lat_deg: float, lon_deg: float, alt_m: float) -> tuple[float, float, float]:
    """(lat_deg, lon_deg, alt_m AMSL) -> local NED (m) around `home`."""
    return Projection(home).to_local(lat_deg, lon_deg, alt_m)
