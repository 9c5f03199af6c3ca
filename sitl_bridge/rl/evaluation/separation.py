"""Separation between drones in evaluated episodes: the least distance between any two drones,
and how many episodes lost separation (came closer than the minimum).

Distances are taken at the positions the rollouts record (`Trace.positions_enu_m`: after reset
and after every step), so between two decisions a closer pass can go unseen; both drones count
only while both are still flying their episode."""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

from sitl_bridge.rl.evaluation.rollout import Trace

SEPARATION_M = 1.0
"""Loss of separation: two drones closer than this (m, centre to centre)."""


@dataclass(frozen=True)
class Separation:
    """Over the multi-drone episodes of an evaluation."""

    episodes: int
    """Episodes with at least two drones whose positions were recorded."""
    lost: int
    """Of them, those where two drones came closer than `minimum_m`."""
    minimum_m: float
    least_m: float | None
    """The least distance seen in any episode (None: no episode counted)."""

    @property
    def rate(self) -> float:
        return self.lost / self.episodes if self.episodes else 0.0

    def to_dict(self) -> dict:
        return {**asdict(self), "rate": self.rate}

    def summary(self) -> str:
        if not self.episodes:
            return "separation: no multi-drone episode"
        return (f"loss of separation (< {self.minimum_m:g} m): {self.rate:.0%} ({self.lost} of {self.episodes} "
                f"episodes), least distance {self.least_m:.2f} m")


def episode_least_distance(traces: Sequence[Trace]) -> float | None:
    """The least distance between any two of one episode's drones at the recorded steps."""
    paths = [np.asarray(t.positions_enu_m, dtype=float).reshape(-1, 3) for t in traces if t.positions_enu_m]
    least = None
    for i in range(len(paths)):
        for j in range(i):
            steps = min(len(paths[i]), len(paths[j]))  # a drone's trace ends with its episode
            if steps:
                d = float(np.min(np.linalg.norm(paths[i][:steps] - paths[j][:steps], axis=1)))
                least = d if least is None else min(least, d)
    return least


def separation(traces: Sequence[Trace], minimum_m: float = SEPARATION_M) -> Separation:
    """Loss of separation over the episodes of `traces` (grouped by `Trace.episode`)."""
    episodes: dict[int, list[Trace]] = defaultdict(list)
    for trace in traces:
        episodes[trace.episode].append(trace)
    least = [d for d in (episode_least_distance(group) for group in episodes.values()) if d is not None]
    return Separation(episodes=len(least), lost=sum(d < minimum_m for d in least), minimum_m=minimum_m,
                      least_m=min(least) if least else None)
