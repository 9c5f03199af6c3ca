"""Temporally extended epsilon-greedy exploration ("ez-greedy": Dabney, Ostrovski and Barreto,
"Temporally-Extended epsilon-Greedy Exploration", ICLR 2021).

Plain epsilon-greedy explores by single random steps: with 1 m actions that is a random walk,
which strays about sqrt(45) ~ 7 m in a 45-step episode and seldom finds a goal round two blocks
(`experiments/generalization/two_blocks.yaml`, seeds 1 and 5). ez-greedy keeps the exploration
rate, but an exploring step starts a run: the random action is repeated for n steps, n drawn
from a zeta distribution truncated at `explore_repeat_max` (P(n) proportional to
n^-`explore_repeat_exponent`), so most detours stay short and now and then one crosses the
workspace. No greedy decision is taken during a run. Off (plain epsilon-greedy, the thesis's)
unless a scenario's `train:` sets `explore_repeat_max` above 1; runs end at episode ends, so a
resume from a checkpoint continues exactly.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def repeat_probabilities(max_repeat: int, exponent: float) -> np.ndarray:
    """P(n) for run lengths n = 1..max_repeat: n^-exponent, normalised."""
    weights = np.arange(1, max_repeat + 1, dtype=float) ** -exponent
    return weights / weights.sum()


class RepeatedExploration:
    """ez-greedy action choice for every drone of an episode (one run per drone)."""

    def __init__(self, greedy: Callable[[np.ndarray], int], n_actions: int, max_repeat: int, exponent: float) -> None:
        self.greedy = greedy
        self.n_actions = n_actions
        self.probabilities = repeat_probabilities(max_repeat, exponent)
        self.runs: dict[int, tuple[int, int]] = {}
        """drone -> (action being repeated, steps of the run still to come)."""

    def start_episode(self) -> None:
        """Runs do not cross episodes."""
        self.runs.clear()

    def act(self, drone: int, obs: np.ndarray, epsilon: float, rng: np.random.Generator) -> int:
        """The next step of the drone's run, else random with probability epsilon (starting a
        run of a drawn length), else the greedy action."""
        action, left = self.runs.get(drone, (0, 0))
        if left > 0:
            self.runs[drone] = (action, left - 1)
            return action
        # the same two draws as plain epsilon-greedy (`DQNAgent.act`), then the run's length
        explore = rng.random() < epsilon
        random_action = int(rng.integers(self.n_actions))
        if not explore:
            return self.greedy(obs)
        length = 1 + int(rng.choice(len(self.probabilities), p=self.probabilities))
        self.runs[drone] = (random_action, length - 1)
        return random_action
