"""Seeds of the per-vehicle sensor noise."""

from __future__ import annotations


def sensor_seed(seed: int, vehicle: int) -> int:
    """Seed of vehicle `vehicle`'s sensor noise in a session (or episode) seeded `seed`; the
    same in every backend, so `direct` and `stub` draw the same noise."""
    return int(seed) * 1000 + vehicle
