"""Rule extraction: fly the greedy policy over randomised episodes and describe its behaviour.

The thesis turned logged action strings into traffic rules by hand ("ER: 6 6 6 6 6 6",
"O: 3 5 5 3 3 3 3 4 4 - fly over the obstacle"). This module does the reading for the human:
action histograms, the most common action sequences (run-length compressed), and geometric facts
from the flown paths (climb above the straight start-goal path, sideways deviation to the left or
right of the direction of travel, hovering), turned into short statements.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import asdict, dataclass, field

import numpy as np

from sitl_bridge.rl.common.action_names import action_name
from sitl_bridge.rl.evaluation.rollout import Trace

CLIMB_OVER_M = 0.8
"""Rising this far above both start and goal altitude counts as flying over something."""
SIDESTEP_M = 0.8
"""Leaving the straight start-goal line sideways by this much counts as passing to a side."""


_SWAPPED = {0: 1, 1: 0, 2: 3, 3: 2}
"""A `swap_drones` drone flies code 0 as 1 and 2 as 3 (world frame, `envs/actions.py`)."""


def flown_name(code: int, frame: str = "world", swapped: bool = False) -> str:
    """What action `code` makes a drone do, named in the scenario's action `frame`
    (`swapped`: the drone is in the world frame's `swap_drones`, so 0 flies west)."""
    return action_name(_SWAPPED.get(code, code) if swapped else code, frame)


def run_length(actions: list[int]) -> str:
    """`6 6 6 3 3` -> `6x3 3x2`."""
    parts: list[str] = []
    for code in actions:
        if parts and parts[-1][0] == code:
            parts[-1][1] += 1
        else:
            parts.append([code, 1])
    return " ".join(f"{c}" if n == 1 else f"{c}x{n}" for c, n in parts)


@dataclass
class PathGeometry:
    """What a flown path did relative to the straight line from start to goal."""

    climb_above_m: float
    """Highest altitude minus the higher of start and goal altitude."""
    lateral_m: float
    """Largest sideways distance from the start-goal line; positive = left of travel direction."""


def path_geometry(trace: Trace) -> PathGeometry | None:
    """Geometry of one trace (None without positions or goal)."""
    if len(trace.positions_enu_m) < 2 or trace.goal_enu_m is None:
        return None
    path = np.asarray(trace.positions_enu_m, dtype=float)
    start, goal = path[0], np.asarray(trace.goal_enu_m, dtype=float)
    climb = float(path[:, 2].max() - max(start[2], goal[2]))
    direction = goal[:2] - start[:2]
    norm = float(np.linalg.norm(direction))
    lateral = 0.0
    if norm > 1e-6:
        offsets = path[:, :2] - start[:2]
        cross = (direction[0] * offsets[:, 1] - direction[1] * offsets[:, 0]) / norm  # > 0: left
        lateral = float(cross[np.argmax(np.abs(cross))])
    return PathGeometry(climb, lateral)


@dataclass
class BehaviourSummary:
    """The greedy policy's behaviour over a set of episodes."""

    world: str
    episodes: int
    outcomes: dict[str, float]
    action_share: dict[str, float]
    """Share of every action code among all actions taken (`"6 toward goal": 0.9`)."""
    first_action_share: dict[str, float]
    top_sequences: list[tuple[str, int]]
    """Most common full action sequences (run-length compressed) and how often they occurred."""
    frame: str = "world"
    """The action frame the names are in (`task.action.frame`)."""
    per_drone_action_share: dict[int, dict[str, float]] = field(default_factory=dict)
    climb_over_share: float | None = None
    """Share of successful drone-episodes that rose clearly above start and goal."""
    left_share: float | None = None
    right_share: float | None = None
    """Shares of successful drone-episodes that left the straight line to the left / right."""
    statements: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)

    def report(self) -> str:
        lines = [f"{self.world}: {self.episodes} greedy episodes; outcomes "
                 + ", ".join(f"{k} {v:.0%}" for k, v in self.outcomes.items())]
        lines += [f"  - {s}" for s in self.statements]
        lines.append(f"  actions ({self.frame} frame): " + ", ".join(f"{k} {v:.0%}" for k, v in self.action_share.items()))
        for drone, share in self.per_drone_action_share.items():
            lines.append(f"  drone {drone}: " + ", ".join(f"{k} {v:.0%}" for k, v in share.items()))
        lines.append("  typical sequences:")
        lines += [f"    {n:4d} x  {seq}" for seq, n in self.top_sequences]
        return "\n".join(lines)


def _shares(counter: Counter, total: int, frame: str, swapped: bool = False) -> dict[str, float]:
    if not total:
        return {}
    return {f"{code} {flown_name(code, frame, swapped)}": count / total for code, count in counter.most_common()}


def summarize_behaviour(world: str, episodes: int, traces: list[Trace], top: int = 5, *,
                        frame: str = "world", swap_drones: tuple[int, ...] = ()) -> BehaviourSummary:
    """Histograms, typical sequences and statements for a set of greedy rollouts; actions are
    named in the scenario's action `frame` (`task.action.frame`), per drone with its
    `swap_drones` applied (the pooled shares name the unswapped meaning)."""
    all_actions = Counter(a for t in traces for a in t.actions)
    total = sum(all_actions.values())
    outcomes = Counter(t.outcome for t in traces)
    summary = BehaviourSummary(
        world=world, episodes=episodes,
        outcomes={k: v / len(traces) for k, v in outcomes.most_common()} if traces else {},
        action_share=_shares(all_actions, total, frame),
        first_action_share=_shares(Counter(t.actions[0] for t in traces if t.actions), len(traces), frame),
        top_sequences=Counter(run_length(t.actions) for t in traces).most_common(top),
        frame=frame,
    )
    drones = sorted({t.drone for t in traces})
    if len(drones) > 1:
        for drone in drones:
            mine = Counter(a for t in traces if t.drone == drone for a in t.actions)
            summary.per_drone_action_share[drone] = _shares(mine, sum(mine.values()), frame,
                                                            drone in swap_drones)

    wins = [g for t in traces if t.outcome == "goal" and (g := path_geometry(t)) is not None]
    if wins:
        summary.climb_over_share = float(np.mean([g.climb_above_m >= CLIMB_OVER_M for g in wins]))
        summary.left_share = float(np.mean([g.lateral_m >= SIDESTEP_M for g in wins]))
        summary.right_share = float(np.mean([g.lateral_m <= -SIDESTEP_M for g in wins]))
    summary.statements = _statements(summary, all_actions, total, wins, frame)
    return summary


def _statements(summary: BehaviourSummary, actions: Counter, total: int, wins: list[PathGeometry],
                frame: str) -> list[str]:
    out: list[str] = []
    if total:
        code, count = actions.most_common(1)[0]
        share = count / total
        word = "mostly" if share >= 0.5 else "most often"
        out.append(f"{word} action {code} ({action_name(code, frame)}): {share:.0%} of all actions")
    if summary.climb_over_share is not None:
        if summary.climb_over_share >= 0.5:
            climbs = [g.climb_above_m for g in wins if g.climb_above_m >= CLIMB_OVER_M]
            out.append(f"climbs over: {summary.climb_over_share:.0%} of successful flights rise "
                       f"{np.median(climbs):.1f} m (median) above start and goal, then descend")
        if (summary.left_share or 0) >= 0.3 or (summary.right_share or 0) >= 0.3:
            out.append(f"leaves the straight line: to its left in {summary.left_share:.0%}, to its right in "
                       f"{summary.right_share:.0%} of successful flights")
        if summary.climb_over_share < 0.5 and (summary.left_share or 0) < 0.3 and (summary.right_share or 0) < 0.3:
            out.append("flies the straight start-goal line (no climb-over, no sidestep)")
    hover = actions.get(7, 0) / total if total else 0.0
    if hover >= 0.15:
        out.append(f"hovers (action 7) in {hover:.0%} of its steps: waits")
    for drone, share in summary.per_drone_action_share.items():
        if share:
            name, value = next(iter(share.items()))
            out.append(f"drone {drone}: mostly {name} ({value:.0%})")
    return out
