"""A warning for runs that learn to end their episodes early before they have found the goal.

While no goal has been reached, a crash (or leaving the workspace) can be the best return an
agent knows: step-limited episodes bootstrap, so flying on without the goal is worth
`per_step / (1 - gamma)` to it (-500 for the thesis's -5 at gamma 0.99), and a -100 crash is
the cheaper end. Seen in `experiments/generalization/two_blocks.yaml` (seeds 1 and 5: every
episode a crash within 3-4 steps for 1500 episodes). `EarlyEndWatch` says so once, when a whole
window of drone-episodes has no goal and nearly all of them crashed or left the workspace early,
so that a researcher trying a scenario of their own learns it in minutes, not after the budget.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable
from typing import TYPE_CHECKING

from sitl_bridge.rl.common.episode_log import EpisodeRecord

if TYPE_CHECKING:
    from sitl_bridge.envs.scenario import Scenario

WINDOW = 600
"""Drone-episodes looked at (the most recent ones). Replayed over the 159 runs under docs/results
(session 13), 600 warned in 3, all of which failed (`two_blocks` seeds 1 and 5 at episodes 656
and 621 of 1500, an old TW recipe's seed 1), and in no run that succeeded; 200 also warned in 7
runs that found the goal later (`two_blocks` seeds 2, 3 and 6 after 400-600 episodes)."""
EARLY_END_SHARE = 0.9
"""Share of the window that must have crashed or left the workspace early."""
EARLY_FRACTION = 0.25
"""An end is early within this fraction of the scenario's step limit."""


def flying_on_value(per_step: float, gamma: float) -> float | None:
    """What flying on forever is worth to a bootstrapping agent that never reaches the goal (None
    for gamma 1: unbounded)."""
    return per_step / (1.0 - gamma) if gamma < 1.0 else None


class EarlyEndWatch:
    """Watches finished drone-episodes; `add` returns the warning once, when it first applies."""

    def __init__(self, max_steps: int, rewards: dict[str, float], gamma: float, window: int = WINDOW,
                 guided_episodes: int | None = 0) -> None:
        self.early_steps = max(1, int(EARLY_FRACTION * max_steps))
        self.rewards = rewards
        self.gamma = gamma
        self.guided_episodes = guided_episodes
        """The run's `guided_explore_episodes` (0: off; None: its algorithm has no such option), so that
        the advice fits what it ran with."""
        self.recent: deque[tuple[str, int]] = deque(maxlen=window)
        self.warned = False

    @classmethod
    def of(cls, scenario: Scenario | None, gamma: float, guided_episodes: int | None = 0) -> EarlyEndWatch | None:
        """The watch for `scenario` (None for an env without a scenario, e.g. a test's toy env)."""
        if scenario is None:
            return None
        return cls(scenario.task.max_steps, {term.name: term.step_scale for term in scenario.task.rewards}, gamma,
                   guided_episodes=guided_episodes)

    def add(self, records: Iterable[EpisodeRecord]) -> str | None:
        """Count `records`; the warning text the first time the window shows the pattern."""
        self.recent.extend((r.outcome, r.steps) for r in records)
        if self.warned or len(self.recent) < (self.recent.maxlen or 0):
            return None
        if any(outcome == "goal" for outcome, _ in self.recent):
            return None
        early = sum(outcome in ("crash", "out") and steps <= self.early_steps for outcome, steps in self.recent)
        share = early / len(self.recent)
        if share < EARLY_END_SHARE:
            return None
        self.warned = True
        return (f"no goal in the last {len(self.recent)} drone-episodes, and {share:.0%} of them crashed or left "
                f"the workspace within {self.early_steps} steps: the agent is learning to end its episodes early"
                f"{self._why()}. What it lacks is a first goal: {self._remedy()}exploration that travels "
                "(train: explore_repeat_max, ez-greedy) or shaping that leads round obstacles "
                "(closer_to_goal: {along: path}) may give it one, or another seed; see docs/scenarios.md on "
                "scenarios of your own")

    def _remedy(self) -> str:
        """Goal-seeking exploration: the remedy measured on collapsed seeds (docs/findings.md), off by
        default because its guide knows the static obstacles, which the agent does not see."""
        cost = "its guide knows the static obstacles, which the agent does not see"
        if self.guided_episodes is None:
            return ""
        if self.guided_episodes > 0:
            return (f"goal-seeking exploration was on for the first {self.guided_episodes} episodes "
                    f"(train: guided_explore_episodes; {cost}), and more of it (a larger guided_explore_episodes "
                    "or guided_explore_share) may bring goals into the replay; ")
        return ("goal-seeking exploration (train: guided_explore_episodes: 100; off by default: "
                f"{cost}) gave one to most collapsed seeds measured; ")

    def _why(self) -> str:
        per_step, crash = self.rewards.get("per_step"), self.rewards.get("crash")
        value = None if per_step is None else flying_on_value(per_step, self.gamma)
        if value is None or crash is None or crash <= value:
            return ""
        return (f" (until it finds the goal that pays: flying on is worth per_step / (1 - gamma) = {value:.0f} to "
                f"it, since step-limited episodes bootstrap, and a crash {crash:g})")

