"""`make_vec_env`: N independent copies of a single-drone scenario stepped in one process.

Design (measured with `sitl-bridge bench`, key `batched`): each copy is an ordinary `SitlEnv`
with its own pybullet client, wrapped in Gymnasium's `SyncVectorEnv`. A copy is therefore
exactly the env a user makes with `make_env` on the same seed, so observations, rewards and
resets are those of N single envs by construction (tests/test_envs_vector.py checks it), and
no second implementation of the scenario exists; each copy runs its 250 physics steps per
action in one hot loop (the `direct` backend's fused loop).

Alternatives measured (CPU time, 16 copies, steady flight; `tools/vehicle_step_floor.py`
re-measures the floor): stepping all copies in lockstep, one physics step at a time, cost ~23 us
per vehicle-step against ~20 us for this design (16 worlds touched per step: cache misses), and
calling the compiled kernels once per step over all copies (numba typed lists of their state
vectors) ~27 us: batching saves the kernels' dispatch (~1 us a call) but not the per-vehicle
Python (commander, 50/5 Hz sensor and estimator updates, collision tests), and list access
costs more than it saves. One shared pybullet world saves ~0.9 us of `stepSimulation` per copy
but is not bit-identical to single envs: copies 1 km apart round differently in absolute
coordinates, and overlapping copies in separate collision groups still diverged after contacts.
The floor: pybullet's per-body calls (own step ~1.1, state read ~1.45, wrench ~0.5 bare steps)
are ~3 bare steps per vehicle-step; with the ~1.25 physics steps per flown step that episode
starts add, they alone cap `batched` near 0.26 of bare pybullet.

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
