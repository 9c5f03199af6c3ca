"""Env backends behind one `autopilot=` switch: `direct`, `stub`, `px4` (see `base.Backend`)."""

from __future__ import annotations

from sitl_bridge.envs.backends.base import (
    ESTIMATORS,
    Backend,
    BackendError,
    Snapshot,
    check_estimator,
)
from sitl_bridge.world import World

AUTOPILOTS = ("direct", "stub", "px4")


def make_backend(autopilot: str, world: World, *, start_altitude_m: float = 2.5,
                 speed_factor: float = 0.0, seed: int = 0, instance_base: int = 0,
                 px4_bin: str | None = None, gui: bool = False, estimator: str = "sensors") -> Backend:
    """The backend called `autopilot` for `world` (imports only what that backend needs).

    `estimator`: `sensors` (default) or `ground_truth` (see `base.ESTIMATORS`)."""
    if autopilot not in AUTOPILOTS:
        raise ValueError(f"autopilot must be one of {', '.join(AUTOPILOTS)}, got {autopilot!r}")
    check_estimator(estimator, autopilot)
    if autopilot == "direct":
        from sitl_bridge.envs.backends.direct import DirectBackend

        return DirectBackend(world, start_altitude_m=start_altitude_m, seed=seed, gui=gui,
                             estimator=estimator)
    from sitl_bridge.envs.backends.session import SessionBackend

    return SessionBackend(world, autopilot=autopilot, start_altitude_m=start_altitude_m,
                          speed_factor=speed_factor, instance_base=instance_base,
                          px4_bin=px4_bin, gui=gui, estimator=estimator)


__all__ = ["AUTOPILOTS", "ESTIMATORS", "Backend", "BackendError", "Snapshot", "make_backend"]
