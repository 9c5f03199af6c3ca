"""Prioritized experience replay (Schaul et al. 2016), proportional variant.

Transition i is sampled with probability P(i) = p_i^alpha / sum_k p_k^alpha, where p_i is its last
|TD error| + epsilon (new transitions get the largest priority seen so far, so each is replayed
at least once soon). The bias this introduces is corrected by importance-sampling weights
w_i = (N * P(i))^-beta / max_j w_j multiplying each transition's loss.

The priorities live in one float64 array aligned with `ReplayBuffer`'s slots; a checkpoint
stores it as a tensor (no pickle), so a resumed run samples what it would have sampled.

Speed: p_i^alpha is kept per slot beside p_i and recomputed only for the slots that change, so
an update costs a sum, a cumulative sum and a binary search over the filled slots instead of a
power of every priority (the power dominated at 150k rows). The draw repeats numpy's
`Generator.choice(n, size, p=P)` step for step (cumulative sum of P, divided by its last
value, one `random()` per pick, right-sided search), so the slots drawn are bit-identical to
what `choice` drew before this cache existed.
"""

from __future__ import annotations

import numpy as np


def sampling_probabilities(priorities: np.ndarray, alpha: float) -> np.ndarray:
    """P(i) = p_i^alpha / sum_k p_k^alpha."""
    scaled = np.power(priorities, alpha)
    return scaled / scaled.sum()


def importance_weights(probabilities: np.ndarray, picked: np.ndarray, beta: float) -> np.ndarray:
    """w_i = (N * P(i))^-beta, normalised by the largest weight over the whole buffer (<= 1)."""
    n = len(probabilities)
    weights = np.power(n * probabilities[picked], -beta)
    return weights / np.power(n * probabilities.min(), -beta)


def draw_proportional(probabilities: np.ndarray, size: int, rng: np.random.Generator) -> np.ndarray:
    """`size` indices drawn with replacement by `probabilities`: exactly the draws (and the random
    numbers consumed) of `rng.choice(len(probabilities), size, p=probabilities)`, without its
    validation passes over the whole array."""
    cdf = probabilities.cumsum()
    cdf /= cdf[-1]
    return cdf.searchsorted(rng.random(size), side="right").astype(np.int64)


class Priorities:
    """Priority per replay slot, proportional sampling and priority updates."""

    def __init__(self, capacity: int, alpha: float, epsilon: float) -> None:
        self.values = np.zeros(capacity, dtype=np.float64)
        """p_i per slot (what a checkpoint stores)."""
        self.alpha = alpha
        self.epsilon = epsilon
        self.max_priority = 1.0
        self._scaled = np.zeros(capacity, dtype=np.float64)
        """p_i^alpha per slot, kept in step with `values` (module docstring: speed)."""

    def _set(self, slots: np.ndarray, new: np.ndarray) -> None:
        self.values[slots] = new
        # The power of a contiguous copy, as sampling_probabilities computes it on the whole array.
        self._scaled[slots] = np.power(np.ascontiguousarray(self.values[slots]), self.alpha)

    def added(self, slots: np.ndarray) -> None:
        """New transitions in `slots` get the highest priority seen so far."""
        self._set(slots, np.full(len(slots), self.max_priority))

    def restore(self, values: np.ndarray, max_priority: float) -> None:
        """Take the priorities a checkpoint stored."""
        self.values[:] = values
        self._scaled[:] = np.power(self.values, self.alpha)
        self.max_priority = max_priority

    def sample(self, filled: int, batch_size: int, beta: float,
               rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Slots (with replacement) among the first `filled` and their importance weights."""
        scaled = self._scaled[:filled]
        probabilities = scaled / scaled.sum()  # = sampling_probabilities(values[:filled], alpha)
        picked = draw_proportional(probabilities, batch_size, rng)
        return picked, importance_weights(probabilities, picked, beta)

    def update(self, slots: np.ndarray, td_errors: np.ndarray) -> None:
        """p_i = |delta_i| + epsilon for the sampled slots."""
        new = np.abs(td_errors).astype(np.float64) + self.epsilon
        self._set(slots, new)
        self.max_priority = max(self.max_priority, float(new.max()))
