"""A trained policy flown greedily on several autopilot backends on the same reset seeds:
the one implementation behind `sitl-bridge transfer` and the report's `backends` section
(`rl.experiments.backends_section`).

A `BackendFlight` keeps every drone-episode's outcome, steps, distance flown and actions, so two
backends' flights of one policy can be compared episode by episode (`why_differ`): the outcome
split, the steps of the successful episodes, the distance flown per step (a slower velocity
response shows there first) and where the action sequences part.
"""

from __future__ import annotations

import math
import statistics
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sitl_bridge.rl.common.stats import wilson_interval

OUTCOMES = ("goal", "crash", "out", "timeout")
"""Outcomes in the order they are reported (others, e.g. `terminated`, follow)."""
DIFFERENCE_POINTS = 10.0
"""A backend's success or collision rate this many points from the reference's is explained."""
FIRST_FREE_INSTANCE = 100
"""Session backends claim their vehicle instances from here up (px4: in 0..9): off the low
instances users run on."""


@dataclass
class BackendFlight:
    """Greedy episodes of one policy on one backend; lists are per drone-episode, in the
    rollout's order (episode by episode, drones in order), so flights on the same seeds align."""

    autopilot: str
    episodes: int
    seed: int
    """First evaluation seed (`rollout.eval_seeds(seed, episodes)`)."""
    outcomes: list[str] = field(default_factory=list)
    steps: list[int] = field(default_factory=list)
    step_m: list[float | None] = field(default_factory=list)
    """Mean distance flown per step (m), None without positions."""
    actions: list[list[int]] = field(default_factory=list)

    @property
    def drone_episodes(self) -> int:
        return len(self.outcomes)

    def count(self, outcome: str) -> int:
        return sum(o == outcome for o in self.outcomes)

    @property
    def success(self) -> float:
        return self.count("goal") / self.drone_episodes if self.outcomes else 0.0

    @property
    def collision(self) -> float:
        return self.count("crash") / self.drone_episodes if self.outcomes else 0.0

    @property
    def mean_steps_success(self) -> float | None:
        wins = [s for s, o in zip(self.steps, self.outcomes, strict=True) if o == "goal"]
        return float(np.mean(wins)) if wins else None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> BackendFlight:
        return cls(**data)


def outcome_counts(outcomes: Sequence[str]) -> dict[str, int]:
    """Drone-episodes per outcome, the usual outcomes first (zeros included)."""
    counts = Counter(outcomes)
    return {**{o: counts.get(o, 0) for o in OUTCOMES}, **{o: n for o, n in sorted(counts.items()) if o not in OUTCOMES}}


def fly_on_backend(policy: Callable[[np.ndarray], int], world: str | Path, autopilot: str, *, episodes: int,
                   seed: int, speed_factor: float = 0.0, instance_base: int | None = None,
                   px4_bin: str | None = None) -> BackendFlight:
    """Fly `policy` greedily for `episodes` episodes of `world` on `autopilot`, reset seeds
    `eval_seeds(seed, episodes)`, in one env (`instance_base`: its preferred first instance,
    None: `FIRST_FREE_INSTANCE`).
    Raises RuntimeError (e.g. Px4Error) when the backend cannot start."""
    from sitl_bridge.rl.common.drones_env import scenario_env_factory
    from sitl_bridge.rl.evaluation.evaluate import evaluate_policy

    world = str(world)
    extra: dict[str, Any] = {"px4_bin": px4_bin} if px4_bin else {}
    base = FIRST_FREE_INSTANCE if instance_base is None else instance_base
    factory = scenario_env_factory(world, autopilot, speed_factor=speed_factor, instance_base=base, **extra)
    _, traces = evaluate_policy(policy, factory, world=world, episodes=episodes, seed=seed)
    flight = BackendFlight(autopilot, episodes, seed)
    for trace in traces:
        flight.outcomes.append(trace.outcome)
        flight.steps.append(trace.steps)
        flight.actions.append(list(trace.actions))  # codes, or continuous commands (lists)
        path = np.asarray(trace.positions_enu_m, dtype=float)
        moved = np.linalg.norm(np.diff(path, axis=0), axis=1) if len(path) > 1 else np.empty(0)
        flight.step_m.append(float(moved.mean()) if moved.size else None)
    return flight


# -- summaries ---------------------------------------------------------------------------------
def pooled(flights: Sequence[BackendFlight]) -> BackendFlight:
    """The drone-episodes of several flights (e.g. of several seeds) as one."""
    first = flights[0]
    total = BackendFlight(first.autopilot, sum(f.episodes for f in flights), first.seed)
    for f in flights:
        total.outcomes += f.outcomes
        total.steps += f.steps
        total.step_m += f.step_m
        total.actions += f.actions
    return total


def summary(flight: BackendFlight) -> dict[str, Any]:
    """Rates with Wilson 95 % intervals, outcome counts, mean steps of the successful
    drone-episodes and mean distance per step."""
    n = flight.drone_episodes
    moved = [m for m in flight.step_m if m is not None]
    return {"drone_episodes": n, "success": flight.success, "success_ci95": list(wilson_interval(flight.count("goal"), n)),
            "collision": flight.collision, "collision_ci95": list(wilson_interval(flight.count("crash"), n)),
            "outcomes": outcome_counts(flight.outcomes), "mean_steps_success": flight.mean_steps_success,
            "mean_step_m": float(np.mean(moved)) if moved else None}


def same_actions(reference: BackendFlight, other: BackendFlight) -> dict[str, Any]:
    """How many drone-episodes flew the very same actions as on `reference` (same seeds), and
    the median step (1-based) of the first different action among the others."""
    pairs = list(zip(reference.actions, other.actions, strict=False))
    firsts = []
    for a, b in pairs:
        if a != b:
            firsts.append(next((k + 1 for k, (x, y) in enumerate(zip(a, b, strict=False)) if x != y),
                               min(len(a), len(b)) + 1))
    return {"compared": len(pairs), "identical": len(pairs) - len(firsts),
            "first_difference_median": statistics.median(firsts) if firsts else None}


def differs(reference: dict[str, Any], other: dict[str, Any], points: float = DIFFERENCE_POINTS) -> bool:
    """Success or collision rate more than `points` percentage points apart (summaries)."""
    return any(abs(100 * (other[k] - reference[k])) > points + 1e-9 for k in ("success", "collision"))


def why_differ(reference_name: str, reference: BackendFlight, other: BackendFlight) -> str:
    """One line from the data on how `other`'s episodes differ from `reference`'s: the rates, the
    outcome split, the steps of successful episodes, distance per step and the actions."""
    ref, oth = summary(reference), summary(other)
    parts = [f"success {_pct(oth['success'])} vs {_pct(ref['success'])} on {reference_name} "
             f"({100 * (oth['success'] - ref['success']):+.0f} points)"]
    moved = [f"{name} {ref['outcomes'].get(name, 0)} -> {oth['outcomes'].get(name, 0)}"
             for name in outcome_counts(reference.outcomes + other.outcomes)
             if ref["outcomes"].get(name, 0) != oth["outcomes"].get(name, 0)]
    if moved:
        parts.append(f"outcomes of {oth['drone_episodes']} drone-episodes: " + ", ".join(moved))
    if ref["mean_steps_success"] is not None and oth["mean_steps_success"] is not None:
        parts.append(f"successful episodes took {oth['mean_steps_success']:.1f} steps vs "
                     f"{ref['mean_steps_success']:.1f} ({_rel(oth['mean_steps_success'], ref['mean_steps_success'])})")
    if ref["mean_step_m"] and oth["mean_step_m"] is not None:
        parts.append(f"{oth['mean_step_m']:.2f} m flown per step vs {ref['mean_step_m']:.2f} "
                     f"({_rel(oth['mean_step_m'], ref['mean_step_m'])})")
    same = same_actions(reference, other)
    if same["compared"]:
        text = f"same actions in {same['identical']} of {same['compared']} drone-episodes"
        if same["first_difference_median"] is not None:
            text += f", the others part at step {same['first_difference_median']:g} (median)"
        parts.append(text)
    return "; ".join(parts)


def _pct(value: float) -> str:
    return f"{100 * value:.0f} %"


def _rel(value: float, reference: float) -> str:
    return "n/a" if reference == 0 or math.isnan(reference) else f"{100 * (value / reference - 1):+.0f} %"
