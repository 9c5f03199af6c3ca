"""ORCA's settings and how a policy flies ORCA's velocity with discrete action codes: shared by
the world-frame policy (`orca_policy`) and the travel-frame one (`orca_travel`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sitl_bridge.rl.analysis.orca import HalfPlane

OVERSHOOT = 1.5
"""A move is clear when the map is free at its step's end and this many steps along it."""


@dataclass(frozen=True)
class OrcaSettings:
    """ORCA's parameters (defaults: a 1 m separation target with margin for 1 s decisions)."""

    radius_m: float = 0.6
    """Each drone's radius: two keep 1.2 m between centres, above the 1 m separation minimum."""
    time_horizon_s: float = 5.0
    """Conflicts are looked for this far ahead (tau)."""
    vertical_clearance_m: float = 1.2
    """Another drone further above or below than this is no conflict."""


def choose_action(wanted: np.ndarray, planes: list[HalfPlane], candidates: np.ndarray, speed: float,
                  clear: np.ndarray | None = None) -> int:
    """The action code (row of `candidates`, ENU m/s) that flies ORCA's velocity `wanted` best.

    Only codes inside every half-plane (horizontally) are considered while any is; of those, when
    ORCA wants to move (at least half the action speed), the one pointing most nearly its way, ties
    broken to the right of it (both drones of a head-on pair then pass on their right); when it
    wants to nearly stop, the nearest. With none inside, the nearest of all. Pointing rather than
    nearest because the codes move at full speed: a sidestep is then further from a slightly
    deflected velocity than hovering is, and nearest alone would hover in front of every conflict.
    `clear` (per code; default all): codes whose step ends clear of static obstacles; the others
    are never chosen (ORCA here knows only drones, the map knows the walls), unless none is clear."""
    distance = np.linalg.norm(candidates - wanted, axis=1)
    clear = np.ones(len(candidates), dtype=bool) if clear is None or not np.any(clear) else np.asarray(clear)
    allowed = clear & np.array([all(plane.violation(c[:2]) <= 1e-9 for plane in planes) for c in candidates])
    if not allowed.any():
        return int(np.argmin(np.where(clear, distance, np.inf)))
    norm = float(np.linalg.norm(wanted))
    if norm < 0.5 * speed:
        return int(np.argmin(np.where(allowed, distance, np.inf)))
    lengths = np.linalg.norm(candidates, axis=1)
    moving = allowed & (lengths > 1e-9)
    if not moving.any():
        return int(np.argmin(np.where(allowed, distance, np.inf)))
    unit = wanted / norm
    cosine = candidates @ unit / np.maximum(lengths, 1e-9)
    right = -(unit[0] * candidates[:, 1] - unit[1] * candidates[:, 0]) / np.maximum(lengths, 1e-9)
    return int(np.argmax(np.where(moving, cosine + 1e-6 * right, -np.inf)))
