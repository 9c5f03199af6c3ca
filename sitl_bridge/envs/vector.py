"""`make_vec_env`: N independent copies of a single-drone scenario stepped in one process.

Design (measured with `sitl-bridge bench`, key `batched`): each copy is an ordinary `SitlEnv`
with its own pybullet client, wrapped in Gymnasium's `SyncVectorEnv`. A copy is therefore
exactly the env a user makes with `make_env` on the same seed, so observations, rewards and
resets are those of N single envs by construction (tests/test_envs_vector.py checks it), and
no second implementation of the scenario exists. One shared pybullet world with the copies far
apart would save the per-client step overhead (a few microseconds of pybullet's C work, under
10 % of a `direct` step today), but the Python per-vehicle work dominates either way.

Autoreset is Gymnasium's `SAME_STEP` mode: when a copy's episode ends, `step` returns the final
observation in `infos["final_obs"]` and the first observation of the next episode in `obs`, the
way DQN collectors expect (no dummy transition between episodes).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, SyncVectorEnv

from sitl_bridge.envs.options import EnvOptions
from sitl_bridge.envs.single import SitlEnv


def make_vec_env(scenario: str | Path, *, num_envs: int, options: EnvOptions | None = None,
                 **option_values: Any) -> gym.vector.VectorEnv:
    """A `SyncVectorEnv` of `num_envs` copies of `scenario` (file or registered id); options as
    for `make_env` (`autopilot=`, `seed=`, `instance_base=`, ... or `options=` whole).

    Copy k is `make_env(scenario, seed=seed + k, instance_base=instance_base + k, ...)`, so for
    `stub`/`px4` each copy has its own vehicle instance (ports 4560+i, ...). `reset(seed=s)`
    seeds copy k with s + k, as Gymnasium's vector envs do."""
    from sitl_bridge.envs import scenario_path  # the package imports this module

    if not isinstance(num_envs, int) or num_envs < 1:
        raise ValueError(f"make_vec_env: num_envs: expected an integer >= 1, got {num_envs!r}")
    path = scenario_path(scenario)
    base = EnvOptions.of(options, **option_values)

    def factory(k: int):
        copy = replace(base, seed=None if base.seed is None else base.seed + k,
                       instance_base=base.instance_base + k)
        return lambda: SitlEnv(path, options=copy)

    return _SyncVectorEnv([factory(k) for k in range(num_envs)], autoreset_mode=AutoresetMode.SAME_STEP)


class _SyncVectorEnv(SyncVectorEnv):
    """`SyncVectorEnv` whose info arrays fall back to dtype object when a key's values mix
    types across copies (`info["action"]` is None right after a reset, an int after a step)."""

    def _add_info(self, vector_infos: dict, env_info: dict, env_num: int) -> dict:
        try:
            return super()._add_info(vector_infos, env_info, env_num)
        except (TypeError, ValueError):
            widened = {key: value.astype(object) if isinstance(value, np.ndarray) and not key.startswith("_")
                       else value for key, value in vector_infos.items()}
            for key, value in env_info.items():
                if key not in widened and not isinstance(value, dict):
                    widened[key] = np.full(self.num_envs, None, dtype=object)
            return super()._add_info(widened, env_info, env_num)
