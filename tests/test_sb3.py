"""Stable-Baselines3 trains on a registered scenario id, unchanged (the `sb3` extra)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

sb3 = pytest.importorskip("stable_baselines3", reason="Stable-Baselines3 not installed (pip install -e '.[sb3]')")

import sitl_bridge.envs  # noqa: E402,F401  (registers the ids)

ENV_ID = "sitl_bridge/RandomGoal-v0"


def test_sb3_env_checker_accepts_the_env() -> None:
    from stable_baselines3.common.env_checker import check_env

    env = gym.make(ENV_ID)
    try:
        check_env(env.unwrapped, warn=True)
    finally:
        env.close()


@pytest.mark.parametrize("algorithm", ["DQN", "PPO"])
def test_sb3_trains_and_predicts(algorithm: str, tmp_path) -> None:
    env = gym.make(ENV_ID, estimator="ground_truth")
    try:
        cls = getattr(sb3, algorithm)
        kwargs = {"learning_starts": 200, "buffer_size": 5000} if algorithm == "DQN" else {"n_steps": 256}
        model = cls("MlpPolicy", env, seed=0, device="cpu", verbose=0, **kwargs)
        model.learn(total_timesteps=2000)
        model.save(tmp_path / "model")
        loaded = cls.load(tmp_path / "model", device="cpu")
        obs, _ = env.reset(seed=1)
        action, _ = loaded.predict(obs, deterministic=True)
        assert env.action_space.contains(int(action))
        assert model.num_timesteps >= 2000
        assert np.isfinite(obs).all()
    finally:
        env.close()
