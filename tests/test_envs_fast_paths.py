"""The per-decision fast paths change no number: the pruned lidar cast and the one-pass
observation assembly against their references (every ray cast; each feature made finite,
clipped and concatenated on its own), over scripted and random episodes of several scenarios
(discrete and continuous, one and two drones). Real pybullet and stub autopilot."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sitl_bridge.envs import make_env
from sitl_bridge.envs.features import ObservationAssembler
from sitl_bridge.envs.view import DroneView

WORLDS = Path(__file__).resolve().parents[1] / "worlds"


def _reference_observation(features: Any) -> Any:
    """The observation as each feature's own `__call__` builds it, concatenated."""
    return lambda view: np.concatenate([feature(view) for feature in features]).astype(np.float32)


def _episodes(scenario: str, *, reference: bool, seeds: tuple[int, ...] = (1, 2)) -> list[tuple]:
    """Everything the env returned over a scripted and a random episode per seed."""
    env = make_env(WORLDS / scenario, seed=7)
    unwrapped = env.unwrapped
    if reference:
        unwrapped.backend.lidar.prune = False
        unwrapped.runner._observe = _reference_observation(unwrapped.scenario.task.observation)
    action = unwrapped.scenario.task.action
    seen: list[tuple] = []
    try:
        for seed in seeds:
            for scripted in (True, False):
                rng = np.random.default_rng(seed)
                obs, info = env.reset(seed=seed)
                seen.append((obs.tobytes(), info["position_enu_m"].tobytes()))
                for k in range(40 if action.continuous else 12):
                    if action.continuous:
                        a = (np.array([0.1, 0.9, 0.4 if k < 8 else -0.1, 0.3][:action.size], dtype=np.float32)
                             if scripted else rng.uniform(-1.0, 1.0, action.size).astype(np.float32))
                    else:
                        a = (5, 3, 3, 6, 6, 3, 4, 0)[k % 8] if scripted else int(rng.integers(8))
                    obs, reward, terminated, truncated, info = env.step(a)
                    seen.append((obs.tobytes(), reward, terminated, truncated, info["outcome"],
                                 sorted(info["reward_terms"].items()), info["position_enu_m"].tobytes(),
                                 info["crashed"], info["near_obstacle"], info["distance_to_goal_m"]))
                    if terminated or truncated:
                        break
    finally:
        env.close()
    return seen


@pytest.mark.parametrize("scenario", ["obstacle.yaml", "random_obstacle_continuous.yaml", "window_continuous.yaml",
                                      "two_drones_window.yaml", "two_drones_empty_relative_continuous.yaml"])
def test_fast_decisions_return_what_the_reference_paths_return(scenario: str) -> None:
    fast, reference = _episodes(scenario, reference=False), _episodes(scenario, reference=True)
    assert len(fast) == len(reference)
    for a, b in zip(fast, reference, strict=True):
        assert a == b


def test_the_assembled_observation_is_each_feature_clipped_and_concatenated() -> None:
    """Non-finite values and values beyond the bounds, in every feature of a rich scenario."""
    env = make_env(WORLDS / "two_drones_window_relative.yaml", seed=3)
    try:
        env.reset(seed=3)
        features = env.unwrapped.scenario.task.observation
        view: DroneView = env.unwrapped.runner._view(0, env.unwrapped.runner.snapshot, env.unwrapped.runner.snapshot,
                                                     crashed=False)
    finally:
        env.close()
    assemble, reference = ObservationAssembler(features), _reference_observation(features)
    rng = np.random.default_rng(0)
    for _ in range(50):
        wild = rng.choice([np.nan, np.inf, -np.inf, 1e9, -1e9, 0.5], size=3)
        position = np.where(rng.random(3) < 0.5, wild, view.position_enu_m)
        velocity = np.where(rng.random(3) < 0.5, rng.normal(0.0, 8.0, 3), np.nan)
        lidar = {k: np.where(rng.random(v.shape) < 0.3, np.inf, v * rng.uniform(0.0, 2.0)) for k, v in view.lidar.items()}
        wild_view = dataclasses.replace(view, position_enu_m=position, velocity_enu_m_s=velocity, lidar=lidar)
        with np.errstate(invalid="ignore", over="ignore"):  # inf - inf in the relative features: NaN, then 0
            np.testing.assert_array_equal(assemble(wild_view), reference(wild_view))
            assert assemble(wild_view).dtype == np.float32
