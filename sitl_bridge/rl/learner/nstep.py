"""n-step returns: each drone's transitions folded into n-step transitions before the replay.

A 1-step row says "from s, action a gave r and led to s'". An n-step row says "from s_t, action
a_t, then the policy, gave R = r_t + gamma r_{t+1} + ... + gamma^(m-1) r_{t+m-1} and led to
s_{t+m}", with m = n except near the episode's end (m < n there). The TD target of such a row is

    y = R + gamma^m * (1 - done) * Q_target(s_{t+m}, a*)

The replay rows keep the 1-step layout: `reward` holds R and the `terminated` column holds
`1 - gamma^(m-1) * (1 - done)`, so the unchanged 1-step target `r + gamma * (1 - terminated) * V`
equals the n-step one (`gamma * (1 - terminated) = gamma^m`, or 0 after a real end).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass


@dataclass(frozen=True)
class Step:
    """One 1-step transition of one drone (observations are whatever the replay stores)."""

    obs: object
    action: int
    reward: float
    next_obs: object
    terminated: bool


@dataclass(frozen=True)
class NStepRow:
    """A folded transition ready for the replay (`terminated` as described in the module doc)."""

    obs: object
    action: int
    reward: float
    next_obs: object
    terminated: float


def fold(steps: list[Step], gamma: float) -> NStepRow:
    """Fold consecutive steps s_t..s_{t+m-1} into one n-step row (m = len(steps))."""
    ret = 0.0
    for k, step in enumerate(steps):
        ret += gamma ** k * step.reward
    last = steps[-1]
    done = 1.0 if last.terminated else 0.0
    return NStepRow(steps[0].obs, steps[0].action, ret, last.next_obs,
                    1.0 - gamma ** (len(steps) - 1) * (1.0 - done))


class NStepFolder:
    """Per-drone sliding windows of the last n steps; emits a row once a window is full, and the
    shorter tails when the drone's episode ends (terminated or truncated)."""

    def __init__(self, n: int, gamma: float) -> None:
        if n < 1:
            raise ValueError(f"n must be >= 1, got {n}")
        self.n = n
        self.gamma = gamma
        self._windows: dict[int, deque[Step]] = {}

    def push(self, drone: int, step: Step, episode_over: bool) -> list[NStepRow]:
        """Add one step of `drone`; `episode_over` is True on its last step (any end)."""
        window = self._windows.setdefault(drone, deque())
        window.append(step)
        rows: list[NStepRow] = []
        if len(window) == self.n:
            rows.append(fold(list(window), self.gamma))
            window.popleft()
        if episode_over or step.terminated:
            while window:
                rows.append(fold(list(window), self.gamma))
                window.popleft()
            del self._windows[drone]
        return rows
