"""The environment the sensors measure: ISA atmosphere and the Earth's magnetic field (WMM)."""

from __future__ import annotations

import functools
import math

from sitl_bridge.jit import dual
from sitl_bridge.world.schema import GeoHome

SEA_LEVEL_PRESSURE_PA = 101_325.0
SEA_LEVEL_TEMPERATURE_K = 288.15
LAPSE_RATE_K_M = 0.0065
# Gazebo's barometer plugin uses this exponent (g M / (R L) rounded)
PRESSURE_EXPONENT = 5.256
KELVIN_OFFSET = 273.15


def isa_temperature_k(altitude_amsl_m: float) -> float:
    """ISA troposphere temperature (K) at an altitude above mean sea level."""
    return SEA_LEVEL_TEMPERATURE_K - LAPSE_RATE_K_M * altitude_amsl_m


def isa_pressure_pa(altitude_amsl_m: float) -> float:
    """ISA troposphere static pressure (Pa), as Gazebo's barometer plugin computes it."""
    temperature = isa_temperature_k(altitude_amsl_m)
    return SEA_LEVEL_PRESSURE_PA / (SEA_LEVEL_TEMPERATURE_K / temperature) ** PRESSURE_EXPONENT


@dual
def pressure_altitude_m(pressure_pa: float) -> float:
    """Altitude (m AMSL) at which the ISA pressure equals `pressure_pa` (inverse of isa_pressure_pa)."""
    ratio = (SEA_LEVEL_PRESSURE_PA / pressure_pa) ** (1.0 / PRESSURE_EXPONENT)
    return (SEA_LEVEL_TEMPERATURE_K - SEA_LEVEL_TEMPERATURE_K / ratio) / LAPSE_RATE_K_M


@functools.lru_cache(maxsize=64)
def magnetic_field_ned_gauss(home: GeoHome) -> tuple[float, float, float]:
    """Earth's field (north, east, down) in gauss at the home position, from the WMM (pygeomag).

    PX4's EKF compares the measured field's strength and inclination with its own WMM tables,
    so the simulated field must come from the same model. Computed once per home (cached).
    """
    from pygeomag import GeoMag  # imported lazily: loading the coefficients takes a moment

    result = GeoMag().calculate(glat=home.lat_deg, glon=home.lon_deg, alt=home.alt_m / 1000.0,
                                time=home.magnetic_year)
    nt_to_gauss = 1e-5
    return (result.x * nt_to_gauss, result.y * nt_to_gauss, result.z * nt_to_gauss)


def magnetic_declination_inclination_deg(home: GeoHome) -> tuple[float, float]:
    """(declination, inclination) in degrees of the field at home (for checks and logs)."""
    n, e, d = magnetic_field_ned_gauss(home)
    return math.degrees(math.atan2(e, n)), math.degrees(math.atan2(d, math.hypot(n, e)))
