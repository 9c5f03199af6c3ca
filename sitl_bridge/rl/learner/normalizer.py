"""Observation normalisation: running mean and variance of the inputs, applied inside the network.

The statistics are buffers of the Q network (not trained by gradients), so they are saved with
every checkpoint's weights and a greedy policy loaded from a checkpoint normalises exactly as the
trained network did. The online network's statistics are updated with every batch of new
observations (Chan et al.'s parallel merge of mean and variance); the target network keeps the
statistics it was copied with, so it stays the same function until it is re-aligned.
"""

from __future__ import annotations

import torch
from torch import nn

CLIP = 10.0
"""Normalised inputs are clipped to +- this many standard deviations."""


class RunningNorm(nn.Module):
    """x -> clip((x - mean) / sqrt(var + eps), -CLIP, CLIP) with running mean/var over all inputs seen."""

    def __init__(self, size: int, eps: float = 1e-8) -> None:
        super().__init__()
        self.eps = eps
        self.register_buffer("mean", torch.zeros(size, dtype=torch.float64))
        self.register_buffer("var", torch.ones(size, dtype=torch.float64))
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))

    @torch.no_grad()
    def update(self, batch: torch.Tensor) -> None:
        """Merge a batch [B, size] of observations into the statistics."""
        batch = batch.reshape(-1, self.mean.shape[0]).to(torch.float64)
        n = batch.shape[0]
        if n == 0:
            return
        batch_mean = batch.mean(dim=0)
        batch_var = batch.var(dim=0, unbiased=False)
        total = self.count + n
        delta = batch_mean - self.mean
        m2 = self.var * self.count + batch_var * n + delta ** 2 * self.count * n / total
        self.mean.copy_(self.mean + delta * n / total)
        self.var.copy_(m2 / total)
        self.count.copy_(total)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.count <= 0:
            return x
        scaled = (x - self.mean.to(x.dtype)) / torch.sqrt(self.var.to(x.dtype) + self.eps)
        return scaled.clamp(-CLIP, CLIP)
