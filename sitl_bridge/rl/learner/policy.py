"""A trained network as a plain policy: `policy_from_checkpoint(path)(obs) -> action`.

This is how a trained agent flies outside the trainer: evaluation, rule extraction, and
`sitl-bridge run` (through MAVSDK) all call the greedy policy of a checkpoint.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from sitl_bridge.rl.learner.checkpoint import open_checkpoint
from sitl_bridge.rl.learner.checkpoint_fit import RESTORE_ERRORS, unfit
from sitl_bridge.rl.learner.dqn import NetworkShape, QNetwork


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
    return open_checkpoint(path, _network_of, latest=latest)


def _network_of(file: Path, tensors: dict[str, torch.Tensor], state: dict) -> tuple[QNetwork, Path, dict]:
    """The checkpoint's online network; CheckpointCorrupt (try the next one) when its content
    does not make one (a network of another size, a state field of the wrong type)."""
    try:
        network = QNetwork(NetworkShape(**state["network"]))
        network.load_state_dict({k[len("online."):]: v for k, v in tensors.items() if k.startswith("online.")})
        if type(state.get("episode", 0)) is not int:
            raise TypeError(f"episode is {state['episode']!r}, not a count")
    except RESTORE_ERRORS as exc:
        raise unfit(file, exc) from None
    network.eval()
    return network, file, state


def policy_from_checkpoint(path: str | Path, *, latest: bool = False) -> GreedyPolicy:
    """Greedy policy of a run directory (its best greedy checkpoint unless `latest`) or
    checkpoint file: `policy(obs) -> int action`."""
    network, file, state = load_network(path, latest=latest)
    return GreedyPolicy(network, file, state.get("episode", 0))
