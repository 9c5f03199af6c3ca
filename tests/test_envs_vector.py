"""`make_vec_env`: N copies in one process behave exactly as N single envs on the same seeds."""

from __future__ import annotations

import numpy as np
import pytest

from sitl_bridge.envs import make_env
from sitl_bridge.envs.vector import make_vec_env


def test_vec_env_matches_single_envs_through_resets() -> None:
    n, seed = 3, 7
    venv = make_vec_env("sitl_bridge/RandomGoal-v0", num_envs=n, seed=seed)
    singles = [make_env("sitl_bridge/RandomGoal-v0", seed=seed + k) for k in range(n)]
    rng = np.random.default_rng(0)
    try:
        obs, _ = venv.reset(seed=seed)
        for k, env in enumerate(singles):
            np.testing.assert_array_equal(obs[k], env.reset(seed=seed + k)[0])
        ends = 0
        for _ in range(40):
            actions = rng.integers(8, size=n)
            obs, rewards, terminated, truncated, infos = venv.step(actions)
            for k, env in enumerate(singles):
                o, r, term, trunc, _ = env.step(int(actions[k]))
                assert (rewards[k], terminated[k], truncated[k]) == (r, term, trunc)
                if term or trunc:  # same-step autoreset: final obs in infos, next episode's in obs
                    ends += 1
                    np.testing.assert_array_equal(infos["final_obs"][k], o)
                    o, _ = env.reset()
                np.testing.assert_array_equal(obs[k], o)
        assert ends > 0  # the comparison went through at least one reset
    finally:
        venv.close()
        for env in singles:
            env.close()


def test_vec_env_rejects_bad_num_envs() -> None:
    with pytest.raises(ValueError, match="num_envs"):
        make_vec_env("sitl_bridge/Empty-v0", num_envs=0)
