"""Flying an action in slices so that something can watch it (video frames through each action).

An action holds its velocity setpoint for a whole second or more; a video with one frame per
action shows the drone jump. `fly_watched` flies the same setpoint in `FRAME_PERIOD_S` slices and
calls `watch()` after each, when there is a watcher; without one it is the plain `fly` call.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from sitl_bridge.envs.backends.base import Backend, Snapshot

FRAME_PERIOD_S = 0.1
"""Simulated seconds between two watched moments (10 frames per simulated second)."""


def fly_watched(backend: Backend, velocities: Sequence[np.ndarray], duration_s: float,
                watch: Callable[[], None] | None,
                yaws_ned_rad: Sequence[float] | None = None) -> tuple[Snapshot, list[bool]]:
    """`backend.fly(velocities, duration_s)` (with heading setpoints `yaws_ned_rad` when given),
    and with `watch` in slices of `FRAME_PERIOD_S` (when they divide the duration) with
    `watch()` after each. Returns the last snapshot and whether each drone collided at any time
    during it."""
    def fly(seconds: float) -> Snapshot:
        if yaws_ned_rad is None:  # the plain call: backends written before heading setpoints work
            return backend.fly(velocities, seconds)
        return backend.fly(velocities, seconds, yaws_ned_rad)

    slices = round(duration_s / FRAME_PERIOD_S)
    if watch is None or slices < 2 or not math.isclose(slices * FRAME_PERIOD_S, duration_s, abs_tol=1e-9):
        snapshot = fly(duration_s)
        if watch is not None:
            watch()
        return snapshot, list(snapshot.collided)
    collided = [False] * len(velocities)
    for _ in range(slices):
        snapshot = fly(FRAME_PERIOD_S)
        collided = [a or b for a, b in zip(collided, snapshot.collided, strict=True)]
        watch()
    return snapshot, collided
