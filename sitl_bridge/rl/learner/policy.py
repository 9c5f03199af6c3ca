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
from sitl_bridge.rl.learner.policy_file import build_network, online_tensors


@dataclass
class GreedyPolicy:
    """The deterministic policy of a trained network; call it with one observation. A Q network
    (or a discrete SB3 policy, whose outputs are its action logits) gives argmax_a of its
    outputs, an int; a continuous SB3 policy gives its action, an array."""

    network: torch.nn.Module
    source: Path
    episode: int
    """Training episodes behind the weights."""

    @property
    def obs_dim(self) -> int:
        return self.network.shape.obs_dim

    @property
    def n_actions(self) -> int | None:
        """Discrete actions: how many; None for a continuous policy."""
        return self.network.shape.n_actions

    @property
    def continuous(self) -> bool:
        return self.n_actions is None

    @property
    def algorithm(self) -> str:
        return str(getattr(self.network.shape, "algorithm", "dqn"))

    def q_values(self, obs: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return self.network(torch.as_tensor(np.asarray(obs, dtype=np.float32).reshape(-1))).numpy()

    def __call__(self, obs: np.ndarray) -> int | np.ndarray:
        obs = np.asarray(obs, dtype=np.float32).reshape(-1)
        if obs.shape[0] != self.obs_dim:
            raise ValueError(f"{self.source}: the policy takes {self.obs_dim} observation values, got {obs.shape[0]}")
        scores = self.q_values(obs)
        return scores.astype(np.float32) if self.continuous else int(np.argmax(scores))


def require_discrete(policy: GreedyPolicy, what: str) -> GreedyPolicy:
    """`policy`, or a one-line ValueError when it is continuous: `what` (rule extraction,
    distillation) reads discrete action codes and does not support continuous commands yet."""
    if policy.continuous:
        raise ValueError(f"{policy.source}: {what} of a continuous {policy.algorithm} policy is not supported yet "
                         "(it reads discrete action codes); eval, plot, replay, run --policy and export are")
    return policy


def load_network(path: str | Path, *, latest: bool = False) -> tuple[torch.nn.Module, Path, dict]:
    """The online network of a checkpoint file or run directory (its best greedy checkpoint,
    or with `latest` its newest valid one; see `resolve_checkpoint`)."""
    return open_checkpoint(path, _network_of, latest=latest)


def _network_of(file: Path, tensors: dict[str, torch.Tensor], state: dict) -> tuple[torch.nn.Module, Path, dict]:
    """The checkpoint's online network (of whichever algorithm its shape names); CheckpointCorrupt
    (try the next one) when its content does not make one (a network of another size, a state
    field of the wrong type)."""
    try:
        network = build_network(state["network"], online_tensors(tensors))
        if type(state.get("episode", 0)) is not int:
            raise TypeError(f"episode is {state['episode']!r}, not a count")
    except RESTORE_ERRORS as exc:
        raise unfit(file, exc) from None
    return network, file, state


def policy_from_checkpoint(path: str | Path, *, latest: bool = False) -> GreedyPolicy:
    """Greedy policy of a run directory (its best greedy checkpoint unless `latest`) or
    checkpoint file: `policy(obs) -> int action`."""
    network, file, state = load_network(path, latest=latest)
    return GreedyPolicy(network, file, state.get("episode", 0))
