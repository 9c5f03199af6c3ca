"""Experience replay: a fixed-capacity ring of transitions in one numpy structured array.

Row `g` (the g-th transition ever added) lives at slot `g % capacity`, so the buffer can be
rebuilt bit-for-bit from the rows on disk (`replay_store.ReplayStore`) and sampling after a
resume draws exactly what it would have drawn without the interruption.
"""

from __future__ import annotations

import numpy as np
import torch

from sitl_bridge.rl.learner.dqn import Batch
from sitl_bridge.rl.learner.prioritized import Priorities


def transition_dtype(obs_dim: int) -> np.dtype:
    """Structured dtype of one transition row (also the on-disk record layout, little endian)."""
    return np.dtype([
        ("obs", "<f4", (obs_dim,)),
        ("action", "<i4"),
        ("reward", "<f4"),
        ("next_obs", "<f4", (obs_dim,)),
        ("terminated", "<f4"),
    ])


class ReplayBuffer:
    """Ring buffer of the last `capacity` transitions; uniform mini-batch sampling, or
    proportional to priority when `priorities` is given (prioritized replay)."""

    def __init__(self, capacity: int, obs_dim: int, priorities: Priorities | None = None) -> None:
        self.priorities = priorities
        self.capacity = capacity
        self.obs_dim = obs_dim
        self.dtype = transition_dtype(obs_dim)
        self.rows = np.zeros(capacity, dtype=self.dtype)
        self.total_added = 0
        """Transitions ever added (the next row's global index)."""
        self.first_row = 0
        """Global index of the oldest row held (after a replay lost on disk: where it restarted)."""

    def __len__(self) -> int:
        return min(self.total_added - self.first_row, self.capacity)

    def make_rows(self, obs: np.ndarray, actions: np.ndarray, rewards: np.ndarray,
                  next_obs: np.ndarray, terminated: np.ndarray) -> np.ndarray:
        """Pack column arrays (one entry per transition) into rows of this buffer's dtype."""
        rows = np.zeros(len(actions), dtype=self.dtype)
        rows["obs"] = obs
        rows["action"] = actions
        rows["reward"] = rewards
        rows["next_obs"] = next_obs
        rows["terminated"] = terminated
        return rows

    def add_rows(self, rows: np.ndarray) -> None:
        """Append rows (oldest overwritten when full)."""
        if rows.dtype != self.dtype:
            raise ValueError(f"replay rows have dtype {rows.dtype}, expected {self.dtype}")
        for start in range(0, len(rows), self.capacity):
            chunk = rows[start:start + self.capacity]
            slots = (self.total_added + np.arange(len(chunk))) % self.capacity
            self.rows[slots] = chunk
            if self.priorities is not None:
                self.priorities.added(slots)
            self.total_added += len(chunk)

    def restore(self, rows: np.ndarray, total_added: int) -> None:
        """Refill from disk: `rows` are the last transitions of `total_added` ever added."""
        rows = rows[-self.capacity:]
        self.rows[:] = np.zeros(1, dtype=self.dtype)
        self.total_added = self.first_row = total_added - len(rows)
        self.add_rows(rows)

    def sample(self, batch_size: int, rng: np.random.Generator, device: torch.device | str = "cpu") -> Batch:
        """A uniform random mini-batch (with replacement) as tensors."""
        index = rng.integers(0, len(self), size=batch_size)
        if len(self) < self.capacity:  # not full yet: the rows held start at slot first_row
            index = (self.first_row + index) % self.capacity
        picked = self.rows[index]
        return rows_to_batch(picked, device)

    def sample_prioritized(self, batch_size: int, beta: float, rng: np.random.Generator,
                           device: torch.device | str = "cpu") -> Batch:
        """A mini-batch drawn by priority, with its slots and importance weights."""
        assert self.priorities is not None, "sample_prioritized needs a buffer with priorities"
        slots, weights = self.priorities.sample(len(self), batch_size, beta, rng)
        batch = rows_to_batch(self.rows[slots], device)
        batch.slots = slots
        batch.weights = torch.as_tensor(weights.astype(np.float32), device=device)
        return batch


def rows_to_batch(rows: np.ndarray, device: torch.device | str = "cpu") -> Batch:
    """Transition rows -> a Batch of tensors."""
    return Batch(
        obs=torch.as_tensor(np.ascontiguousarray(rows["obs"]), device=device),
        actions=torch.as_tensor(rows["action"].astype(np.int64), device=device),
        rewards=torch.as_tensor(np.ascontiguousarray(rows["reward"]), device=device),
        next_obs=torch.as_tensor(np.ascontiguousarray(rows["next_obs"]), device=device),
        terminated=torch.as_tensor(np.ascontiguousarray(rows["terminated"]), device=device),
    )
