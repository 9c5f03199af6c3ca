"""Stable-Baselines3 algorithms (PPO, SAC, TD3) as the project's learners: built from a scenario's
`train:` section, their networks described by a plain-JSON shape, their state as tensors.

SB3 is the implementation; nothing here re-implements an algorithm. What this module adds:
- (`rl/learner/sb3_arguments.py` checks the `train.<algorithm>` mapping, without torch;)
- `build_model`: the SB3 model for an observation/action space (`SpacesEnv` gives SB3 the
  spaces; the trainer flies the real env itself, episode by episode);
- `SB3Network`: an SB3 policy as a module with the `shape` the project's policy files,
  checkpoints and greedy policies read (`rl/learner/policy_file.py` dispatches on its
  `algorithm`); its forward gives the deterministic action's scores (discrete: the action
  logits, continuous: the action itself);
- `model_tensors` / `load_model_tensors`: every network, optimizer and learned variable as
  tensors (optimizers as `torch.save` bytes read back with `weights_only=True`): no pickle.
"""

from __future__ import annotations

import io
from dataclasses import asdict, dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from torch import nn

from sitl_bridge.errors import ConfigError
from sitl_bridge.rl.learner.sb3_arguments import (
    OFF_POLICY,
    action_noise_sigma,
    policy_kwargs_names,
    sb3_class,
)

ACTIVATIONS = {"tanh": nn.Tanh, "relu": nn.ReLU, "elu": nn.ELU, "leaky_relu": nn.LeakyReLU, "silu": nn.SiLU}


def _policy_kwargs(value: Any, source: str) -> dict[str, Any]:
    """SB3 policy_kwargs from plain data (checked by `sb3_arguments`): `activation_fn` by name."""
    kwargs = policy_kwargs_names(value, source)
    if "activation_fn" in kwargs:
        kwargs["activation_fn"] = ACTIVATIONS[kwargs["activation_fn"]]
    return kwargs


def _action_noise(value: Any, action_dim: int, source: str) -> Any:
    """`{type: normal, sigma: 0.1}` as SB3's NormalActionNoise (None stays None)."""
    sigma = action_noise_sigma(value, source)
    if sigma is None:
        return None
    from stable_baselines3.common.noise import NormalActionNoise

    return NormalActionNoise(np.zeros(action_dim), np.full(action_dim, sigma))



class SpacesEnv(gym.Env):
    """The observation and action spaces of a scenario, for SB3's constructor only (never
    stepped: the trainer flies the real env and feeds SB3's buffers itself)."""

    def __init__(self, observation_space: gym.Space, action_space: gym.Space) -> None:
        self.observation_space, self.action_space = observation_space, action_space

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        raise RuntimeError("SpacesEnv only describes spaces")

    def step(self, action: Any) -> tuple:
        raise RuntimeError("SpacesEnv only describes spaces")


@dataclass(frozen=True)
class SB3Shape:
    """What rebuilds an SB3 policy network: its algorithm, spaces and policy arguments."""

    algorithm: str
    obs_dim: int
    n_actions: int | None = None
    """Discrete actions: how many (None for a continuous action)."""
    action_dim: int | None = None
    """Continuous actions: the Box's size (normalised to [-1, 1])."""
    action_low: list[float] = field(default_factory=list)
    action_high: list[float] = field(default_factory=list)
    policy_kwargs: dict = field(default_factory=dict)
    use_sde: bool = False

    @classmethod
    def of(cls, algorithm: str, obs_dim: int, action_space: gym.Space, arguments: dict[str, Any]) -> SB3Shape:
        if isinstance(action_space, gym.spaces.Discrete):
            action = {"n_actions": int(action_space.n)}
        elif isinstance(action_space, gym.spaces.Box):
            action = {"action_dim": int(np.prod(action_space.shape)),
                      "action_low": [float(v) for v in action_space.low.reshape(-1)],
                      "action_high": [float(v) for v in action_space.high.reshape(-1)]}
        else:
            raise ConfigError(f"{algorithm}: action space {action_space} is neither Discrete nor Box")
        return cls(algorithm, int(obs_dim), **action, policy_kwargs=dict(arguments.get("policy_kwargs") or {}),
                   use_sde=bool(arguments.get("use_sde", False)))

    @property
    def continuous(self) -> bool:
        return self.n_actions is None

    def spaces(self) -> tuple[gym.Space, gym.Space]:
        obs = gym.spaces.Box(-np.inf, np.inf, (self.obs_dim,), np.float32)
        if self.continuous:
            return obs, gym.spaces.Box(np.array(self.action_low, np.float32), np.array(self.action_high, np.float32))
        return obs, gym.spaces.Discrete(self.n_actions)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def build_model(shape: SB3Shape, arguments: dict[str, Any], *, seed: int, device: str | torch.device = "cpu") -> Any:
    """The SB3 model of `shape` with the scenario's constructor `arguments` (already checked)."""
    cls = sb3_class(shape.algorithm)
    kwargs = dict(arguments)
    kwargs["policy_kwargs"] = _policy_kwargs(kwargs.get("policy_kwargs") or {}, f"train.{shape.algorithm}.policy_kwargs")
    if "action_noise" in kwargs:
        kwargs["action_noise"] = _action_noise(kwargs["action_noise"], shape.action_dim or 1,
                                               f"train.{shape.algorithm}.action_noise")
    if isinstance(kwargs.get("train_freq"), list):
        kwargs["train_freq"] = tuple(kwargs["train_freq"])  # YAML has no tuples: [1, episode]
    try:
        model = cls("MlpPolicy", SpacesEnv(*shape.spaces()), seed=seed, device=device, verbose=0, **kwargs)
    except (ValueError, TypeError, AssertionError) as exc:
        hint = (" (SAC and TD3 need continuous actions: a scenario whose task.action is a velocity command)"
                if shape.algorithm in OFF_POLICY and not shape.continuous else "")
        raise ConfigError(f"train.{shape.algorithm}: {' '.join(str(exc).split())}{hint}") from None
    from stable_baselines3.common.logger import configure

    model.set_logger(configure(folder=None, format_strings=[]))  # the run directory has its own logs
    return model


class SB3Network(nn.Module):
    """An SB3 policy with the project's network interface: `shape` (obs_dim, n_actions,
    to_dict) and a forward pass giving the deterministic action's scores: the action logits of
    a discrete policy (its greedy action is their argmax) or a continuous policy's action."""

    def __init__(self, shape: SB3Shape, policy: nn.Module) -> None:
        super().__init__()
        self.shape = shape
        self.policy = policy

    @classmethod
    def build(cls, shape: dict[str, Any], tensors: dict[str, torch.Tensor]) -> SB3Network:
        """The network of a saved `shape` holding `tensors` (its state_dict), in eval mode."""
        sb3_shape = SB3Shape(**shape)
        arguments: dict[str, Any] = {"policy_kwargs": sb3_shape.policy_kwargs, "use_sde": sb3_shape.use_sde}
        if sb3_shape.algorithm in OFF_POLICY:
            arguments.update(buffer_size=1, learning_starts=0)  # the policy alone: no replay to allocate
            if sb3_shape.algorithm == "td3":
                arguments.pop("use_sde")
        network = cls(sb3_shape, build_model(sb3_shape, arguments, seed=0).policy)
        network.load_state_dict(tensors)
        network.eval()
        return network

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        batch = obs.reshape(-1, self.shape.obs_dim).to(torch.float32)
        if self.shape.continuous:
            action = self.policy._predict(batch, deterministic=True)
            low, high = torch.tensor(self.shape.action_low), torch.tensor(self.shape.action_high)
            if self.policy.squash_output:  # SAC/TD3 act in [-1, 1]: unscaled to the Box as SB3's predict does
                action = low + 0.5 * (action + 1.0) * (high - low)
            else:  # PPO's Gaussian: SB3 clips to the Box
                action = torch.clamp(action, low, high)
            scores = action
        else:
            scores = self.policy.get_distribution(batch).distribution.logits
        return scores.reshape(*obs.shape[:-1], -1) if obs.dim() > 1 else scores.reshape(-1)


def model_tensors(model: Any) -> dict[str, torch.Tensor]:
    """Everything learned of an SB3 model: `online.policy.*` (the policy's state_dict, as an
    `SB3Network` names it), `optim.<name>` (optimizer state_dict bytes) and `var.<name>`."""
    state_dicts, variables = model._get_torch_save_params()
    tensors: dict[str, torch.Tensor] = {f"online.policy.{k}": v for k, v in model.policy.state_dict().items()}
    for name in state_dicts:
        if name == "policy":
            continue
        buffer = io.BytesIO()
        torch.save(_attribute(model, name).state_dict(), buffer)
        tensors[f"optim.{name}"] = torch.frombuffer(bytearray(buffer.getvalue()), dtype=torch.uint8)
    for name in variables:
        tensors[f"var.{name}"] = _attribute(model, name).detach().clone()
    return tensors


def load_model_tensors(model: Any, tensors: dict[str, torch.Tensor]) -> None:
    """Put `model_tensors`' output back into `model` (optimizers read with weights_only=True)."""
    prefix = "online.policy."
    model.policy.load_state_dict({k[len(prefix):]: v for k, v in tensors.items() if k.startswith(prefix)})
    state_dicts, variables = model._get_torch_save_params()
    for name in state_dicts:
        if name != "policy":
            state = torch.load(io.BytesIO(tensors[f"optim.{name}"].numpy().tobytes()), weights_only=True)
            _attribute(model, name).load_state_dict(state)
    for name in variables:
        with torch.no_grad():
            _attribute(model, name).copy_(tensors[f"var.{name}"])


def policy_tensors(tensors: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The policy's own state_dict (no prefix) out of `model_tensors`' output."""
    prefix = "online.policy."
    return {k[len(prefix):]: v for k, v in tensors.items() if k.startswith(prefix)}


def _attribute(model: Any, dotted: str) -> Any:
    for part in dotted.split("."):
        model = getattr(model, part)
    return model
