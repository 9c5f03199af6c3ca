"""Env backends behind one `autopilot=` switch (see `base.Backend`); which class serves which
kind is the autopilot registry's (`sitl_bridge.autopilot.registry`)."""

from __future__ import annotations

from sitl_bridge.autopilot.registry import env_kind
from sitl_bridge.envs.backends.base import (
    EPISODE_START,
    Backend,
    BackendError,
    EpisodeStart,
    Snapshot,
)
from sitl_bridge.envs.options import ESTIMATORS, EnvOptions
from sitl_bridge.world import World


def make_backend(world: World, options: EnvOptions, *, start_altitude_m: float = 2.5,
                 takeoff: bool = False) -> Backend:
    """The backend of `options.autopilot` for `world` (imports only what that backend needs);
    with `options.standby`, that backend in worker processes with a standby copy."""
    if options.standby:
        from sitl_bridge.envs.backends.standby import StandbyBackend

        return StandbyBackend(world, options, start_altitude_m=start_altitude_m, takeoff=takeoff)
    return env_kind(options.autopilot).backend_class()(world, options, start_altitude_m=start_altitude_m,
                                                       takeoff=takeoff)


__all__ = ["EPISODE_START", "ESTIMATORS", "Backend", "BackendError", "EpisodeStart", "Snapshot", "make_backend"]
