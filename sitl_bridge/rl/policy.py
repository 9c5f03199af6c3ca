"""A trained network as a plain policy: `policy_from_checkpoint(path)(obs) -> action`.

This is how a trained agent flies outside the trainer: evaluation, rule extraction, and
`sitl-bridge run` (through MAVSDK) all call the greedy policy of a checkpoint.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from sitl_bridge.rl.checkpoint import resolve_checkpoint
from sitl_bridge.rl.dqn import NetworkShape, QNetwork


@dataclass
class GreedyPolicy:
    """argmax_a Q(obs, a) of a trained Q network; call it with one observation."""

    network: QNetwork
    source: Path
    episode: int
    """Training episodes behind the weights."""

    @property
    def obs_dim(self) -> int:
        return self.network.shape.obs_dim

    @property
    def n_actions(self) -> int:
        return self.network.shape.n_actions

    def q_values(self, obs: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return self.network(torch.as_tensor(np.asarray(obs, dtype=np.float32).reshape(-1))).numpy()

    def __call__(self, obs: np.ndarray) -> int:
        obs = np.asarray(obs, dtype=np.float32).reshape(-1)
        if obs.shape[0] != self.obs_dim:
            raise ValueError(f"{self.source}: the policy takes {self.obs_dim} observation values, got {obs.shape[0]}")
        return int(np.argmax(self.q_values(obs)))


def load_network(path: str | Path, *, latest: bool = False) -> tuple[QNetwork, Path, dict]:
    """The online Q network of a checkpoint file or run directory (its best greedy checkpoint,
    or with `latest` its newest valid one; see `resolve_checkpoint`)."""
    file, tensors, state = resolve_checkpoint(path, latest=latest)
    network = QNetwork(NetworkShape(**state["network"]))
    network.load_state_dict({k[len("online."):]: v for k, v in tensors.items() if k.startswith("online.")})
    network.eval()
    return network, file, state


def policy_from_checkpoint(path: str | Path, *, latest: bool = False) -> GreedyPolicy:
    """Greedy policy of a run directory (its best greedy checkpoint unless `latest`) or
    checkpoint file: `policy(obs) -> int action`."""
    network, file, state = load_network(path, latest=latest)
    return GreedyPolicy(network, file, int(state.get("episode", 0)))
