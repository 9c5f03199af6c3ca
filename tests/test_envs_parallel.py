"""Multi-drone PettingZoo ParallelEnv on the `direct` backend (real pybullet, stub autopilot)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

from sitl_bridge.envs import PARALLEL_ENVS, make_parallel_env

WORLDS = Path(__file__).resolve().parents[1] / "worlds"


@pytest.mark.parametrize("env_id", list(PARALLEL_ENVS))
def test_parallel_api_on_the_multi_drone_scenarios(env_id: str) -> None:
    env = make_parallel_env(env_id, seed=0)
    try:
        parallel_api_test(env, num_cycles=12)
        assert env.possible_agents == ["drone0", "drone1"]
    finally:
        env.close()


def test_head_on_flight_crashes_both_drones() -> None:
    env = make_parallel_env(WORLDS / "two_drones_empty.yaml", seed=0)
    try:
        observations, infos = env.reset(seed=0)
        assert set(observations) == {"drone0", "drone1"}
        outcomes: dict[str, str] = {}
        for _ in range(12):
            # action 3 is north for drone0 and, with the thesis's swap, south for drone1
            _, rewards, terminations, truncations, infos = env.step({a: 3 for a in env.agents})
            for agent, done in terminations.items():
                if done:
                    outcomes[agent] = infos[agent]["outcome"]
                    assert rewards[agent] < -50  # the crash term dominates
            if not env.agents:
                break
        assert outcomes == {"drone0": "crash", "drone1": "crash"}
    finally:
        env.close()


def test_each_drone_has_its_own_observation_and_goal() -> None:
    env = make_parallel_env("sitl_bridge/TwoDronesWindow-v0", seed=0)
    try:
        observations, infos = env.reset(seed=4)
        assert not np.array_equal(observations["drone0"], observations["drone1"])
        assert infos["drone0"]["goal_enu_m"][1] > 0 > infos["drone1"]["goal_enu_m"][1]
        # explicit priorities: drone0 starts further south -> lower priority (index 7, 8)
        assert observations["drone0"][7] == 0.0 and observations["drone0"][8] == 1.0
        assert observations["drone1"][7] == 1.0 and observations["drone1"][8] == 0.0
        # transponder: drone0 sees drone1's position
        np.testing.assert_allclose(observations["drone0"][12:15], infos["drone1"]["position_enu_m"],
                                   atol=1e-5)
        assert env.state().shape == (2 * env.observation_space("drone0").shape[0],)
    finally:
        env.close()


def test_a_finished_drone_leaves_and_hovers() -> None:
    env = make_parallel_env(WORLDS / "two_drones_empty.yaml", seed=0)
    try:
        env.reset(seed=1)
        # drone0 flies up out of the 6 m workspace; drone1 hovers
        for _ in range(8):
            _, _, terminations, _, infos = env.step({a: (5 if a == "drone0" else 7) for a in env.agents})
            if "drone0" not in env.agents:
                break
        assert env.agents == ["drone1"]
        assert infos["drone0"]["outcome"] == "out"
        _, rewards, _, _, infos = env.step({"drone1": 7})
        assert set(rewards) == {"drone1"}
    finally:
        env.close()


def test_a_single_drone_scenario_works_as_a_parallel_env() -> None:
    env = make_parallel_env(WORLDS / "random_goal.yaml", seed=0)
    try:
        parallel_api_test(env, num_cycles=5)
        env.reset(seed=2)
        for _ in range(35):
            _, _, _, _, infos = env.step({"drone0": 6})
            if not env.agents:
                break
        assert infos["drone0"]["outcome"] == "goal"
    finally:
        env.close()


def test_seeded_parallel_runs_are_identical() -> None:
    runs = []
    for _ in range(2):
        env = make_parallel_env(WORLDS / "two_drones_window.yaml", seed=0)
        try:
            observations, _ = env.reset(seed=9)
            seen = [observations]
            for step in range(4):
                observations, *_ = env.step({a: (step + k) % 8 for k, a in enumerate(env.agents)})
                seen.append(observations)
            runs.append(seen)
        finally:
            env.close()
    for a, b in zip(*runs, strict=True):
        assert a.keys() == b.keys()
        for agent in a:
            np.testing.assert_array_equal(a[agent], b[agent])
