"""The `train.<algorithm>` mapping of a scenario checked against the Stable-Baselines3 constructor
it feeds (light: no torch import, so the command line starts fast), and the one-line error
naming the `sb3` extra when Stable-Baselines3 is missing."""

from __future__ import annotations

import inspect
from typing import Any

from sitl_bridge.errors import ConfigError

SB3_MISSING = ("Stable-Baselines3 is not installed; install the sb3 extra "
               "(pip install 'sitl-bridge[sb3]') to train with {algorithm}")
CONTROLLED = {
    "policy": "the policy is always SB3's MlpPolicy",
    "env": "the trainer flies the scenario itself",
    "seed": "the run's --seed seeds it",
    "device": "train.device sets it",
    "verbose": "the trainer reports progress",
    "tensorboard_log": "the run directory's tb/ holds TensorBoard",
    "stats_window_size": "train.success_window sets the rolling window",
    "_init_setup_model": "internal",
    "replay_buffer_class": "the replay is saved as arrays of SB3's plain ReplayBuffer",
    "replay_buffer_kwargs": "the replay is saved as arrays of SB3's plain ReplayBuffer",
    "optimize_memory_usage": "the replay is saved as arrays of SB3's plain ReplayBuffer",
    "rollout_buffer_class": "PPO's partial rollout is saved as arrays of SB3's plain RolloutBuffer",
    "rollout_buffer_kwargs": "PPO's partial rollout is saved as arrays of SB3's plain RolloutBuffer",
}
"""Constructor arguments the scenario may not set, and why (one place, for the error message)."""
ACTIVATION_NAMES = ("tanh", "relu", "elu", "leaky_relu", "silu")
OFF_POLICY = ("sac", "td3")


class MissingExtra(ConfigError):
    """Stable-Baselines3 is not installed (the message names the extra to install)."""


def sb3_class(algorithm: str) -> type:
    """The SB3 class of `algorithm`; MissingExtra naming the `sb3` extra when SB3 is missing."""
    try:
        import stable_baselines3
    except ImportError:
        raise MissingExtra(SB3_MISSING.format(algorithm=algorithm)) from None
    return {"ppo": stable_baselines3.PPO, "sac": stable_baselines3.SAC, "td3": stable_baselines3.TD3}[algorithm]


def check_arguments(algorithm: str, arguments: dict[str, Any], source: str, *, needed: bool = True) -> None:
    """Raise ConfigError (one line, naming the key) for an argument the SB3 constructor does not
    take or the trainer controls, or a policy_kwargs value that is not plain data. Without SB3,
    only an algorithm that is `needed` is an error."""
    try:
        cls = sb3_class(algorithm)
    except MissingExtra:
        if needed:
            raise
        return
    known = set(inspect.signature(cls.__init__).parameters) - {"self"}
    for key, value in arguments.items():
        if key in CONTROLLED:
            raise ConfigError(f"{source}.{key}: not settable here ({CONTROLLED[key]})")
        if algorithm in OFF_POLICY and key == "n_steps" and value != 1:
            raise ConfigError(f"{source}.{key}: n-step returns are not supported yet for {algorithm.upper()} "
                              "(they swap in another replay buffer class); leave it at 1")
        if key not in known:
            raise ConfigError(f"{source}.{key}: not a {algorithm.upper()} argument (known: "
                              f"{', '.join(sorted(known - set(CONTROLLED)))})")
        if key == "action_noise":
            action_noise_sigma(value, f"{source}.{key}")
        if key == "policy_kwargs":
            policy_kwargs_names(value, f"{source}.{key}")


def policy_kwargs_names(value: Any, source: str) -> dict[str, Any]:
    """policy_kwargs as plain data (net_arch, activation_fn by name, ...), checked."""
    if not isinstance(value, dict):
        raise ConfigError(f"{source}: expected a mapping (net_arch, activation_fn, ...), got {value!r}")
    name = value.get("activation_fn", "tanh")
    if name not in ACTIVATION_NAMES:
        raise ConfigError(f"{source}.activation_fn: expected one of {', '.join(ACTIVATION_NAMES)}, got {name!r}")
    return dict(value)


def action_noise_sigma(value: Any, source: str) -> float | None:
    """The sigma of `{type: normal, sigma: 0.1}` (None for no noise)."""
    if value is None:
        return None
    if not (isinstance(value, dict) and value.get("type") == "normal" and set(value) <= {"type", "sigma"}
            and isinstance(value.get("sigma"), (int, float)) and value["sigma"] >= 0):
        raise ConfigError(f"{source}: expected {{type: normal, sigma: NUMBER >= 0}}, got {value!r}")
    return float(value["sigma"])
