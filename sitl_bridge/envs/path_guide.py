"""A guide that seeks the goal round static obstacles: the action whose straight move ends
nearest the goal along the shortest obstacle-free path (`path_distance.PathField`).

It is no policy to fly by (it ignores the drone's dynamics and the lidar), only a direction for
exploration: `train: guided_explore_episodes` (rl/training/dqn_training.py) takes it for a share of the
exploring steps of the first episodes, so that the replay holds a goal before the value estimates
settle on ending episodes by a crash (docs/findings.md, the early-crash study).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from sitl_bridge.envs.path_distance import PathField

SAMPLE_M = 0.25
"""Spacing of the points checked along a move (a move through a grown obstacle is no candidate)."""


def guided_action(field: PathField, position_enu_m: np.ndarray, moves_enu_m: Sequence[np.ndarray]) -> int:
    """The index of the move (ENU displacement of each action over one step) whose end has the
    least path distance to the goal among those that stay on free grid nodes all the way; the
    least-moving action when none does."""
    here = np.asarray(position_enu_m, dtype=float)
    best, best_length = None, np.inf
    for code, move in enumerate(moves_enu_m):
        move = np.asarray(move, dtype=float)
        samples = max(1, int(np.ceil(np.linalg.norm(move) / SAMPLE_M)))
        if not all(field.occupancy.free_at(here + move * k / samples) for k in range(1, samples + 1)):
            continue
        length = field.distance(here + move)
        if length < best_length - 1e-9:
            best, best_length = code, length
    if best is None:
        return int(np.argmin([np.linalg.norm(m) for m in moves_enu_m]))
    return best
