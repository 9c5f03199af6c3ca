"""Prioritized experience replay (Schaul et al. 2016), proportional variant.

Transition i is sampled with probability P(i) = p_i^alpha / sum_k p_k^alpha, where p_i is its last
|TD error| + epsilon (new transitions get the largest priority seen so far, so each is replayed
at least once soon). The bias this introduces is corrected by importance-sampling weights
w_i = (N * P(i))^-beta / max_j w_j multiplying each transition's loss.

The priorities live in one float64 array aligned with `ReplayBuffer`'s slots; a checkpoint
stores it as a tensor (no pickle), so a resumed run samples what it would have sampled.
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


class Priorities:
    """Priority per replay slot, proportional sampling and priority updates."""

    def __init__(self, capacity: int, alpha: float, epsilon: float) -> None:
        self.values = np.zeros(capacity, dtype=np.float64)
        self.alpha = alpha
        self.epsilon = epsilon
        self.max_priority = 1.0

    def added(self, slots: np.ndarray) -> None:
        """New transitions in `slots` get the highest priority seen so far."""
        self.values[slots] = self.max_priority

    def sample(self, filled: int, batch_size: int, beta: float,
               rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Slots (with replacement) among the first `filled` and their importance weights."""
        probabilities = sampling_probabilities(self.values[:filled], self.alpha)
        picked = rng.choice(filled, size=batch_size, p=probabilities)
        return picked, importance_weights(probabilities, picked, beta)

    def update(self, slots: np.ndarray, td_errors: np.ndarray) -> None:
        """p_i = |delta_i| + epsilon for the sampled slots."""
        new = np.abs(td_errors).astype(np.float64) + self.epsilon
        self.values[slots] = new
        self.max_priority = max(self.max_priority, float(new.max()))
