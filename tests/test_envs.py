"""Single-drone Gymnasium envs on the `direct` backend: API, scripted thesis policies, determinism,
a scenario added with no code, and the episode-end rules. Real pybullet and stub autopilot."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import sitl_bridge.envs as envs
from sitl_bridge.autopilot.stub.commander import Commander
from sitl_bridge.envs import SINGLE_ENVS, make_env
from sitl_bridge.envs.features import observation_layout

WORLDS = Path(__file__).resolve().parents[1] / "worlds"


def run_actions(env: gym.Env, actions: list[int], seed: int = 0) -> tuple[list[np.ndarray], dict]:
    """Fly `actions` from a seeded reset; observations seen and the last info."""
    obs, info = env.reset(seed=seed)
    seen = [obs]
    for action in actions:
        obs, reward, terminated, truncated, info = env.step(action)
        seen.append(obs)
        assert env.observation_space.contains(obs)
        assert np.isfinite(reward)
        if terminated or truncated:
            break
    return seen, info


@pytest.mark.parametrize("env_id", list(SINGLE_ENVS))
def test_check_env_on_every_single_drone_scenario(env_id: str) -> None:
    env = make_env(env_id, seed=0)
    try:
        check_env(env, skip_render_check=True)
        assert env.action_space == gym.spaces.Discrete(8)
        assert env.observation_space.shape == (env.scenario.task.observation_size,)
    finally:
        env.close()


def test_registered_ids_make_through_gymnasium() -> None:
    env = gym.make("sitl_bridge/Empty-v0")
    try:
        obs, info = env.reset(seed=1)
        assert obs.shape == env.observation_space.shape
        assert info["outcome"] is None and info["reward_terms"] == {}
    finally:
        env.close()


def test_always_toward_goal_reaches_the_random_goal() -> None:
    env = make_env(WORLDS / "random_goal.yaml")
    try:
        goals = []
        for seed in (0, 1, 2):
            _, info = run_actions(env, [6] * env.scenario.task.max_steps, seed=seed)
            assert info["outcome"] == "goal", (seed, info)
            assert info["reward_terms"]["goal_reached"] == 500.0
            goals.append(tuple(info["goal_enu_m"]))
        assert len(set(goals)) == 3  # the goal is re-drawn every episode
    finally:
        env.close()


def test_thesis_solution_flies_over_the_obstacle_to_the_goal() -> None:
    env = make_env(WORLDS / "obstacle.yaml")
    try:
        actions = [3, 5, 5, 3, 3, 3, 3, 4, 4]
        obs, _ = env.reset(seed=0)
        for k, action in enumerate(actions):
            obs, reward, terminated, truncated, info = env.step(action)
            if k < len(actions) - 1:
                assert not (terminated or truncated), (k, info)
            if k == 4:  # above the block
                assert info["position_enu_m"][2] > 4.0
        assert terminated and info["outcome"] == "goal"
        # flying straight at the block crashes instead
        _, info = run_actions(env, [3] * 10, seed=0)
        assert info["outcome"] == "crash"
    finally:
        env.close()


def test_thesis_solution_exits_the_window() -> None:
    env = make_env(WORLDS / "window.yaml")
    try:
        _, info = run_actions(env, [5, 5, 5, 5, 3, 3, 3, 3, 3, 3], seed=0)
        assert info["outcome"] == "goal"
        assert info["position_enu_m"][1] > 4.5  # beyond the north wall
        _, info = run_actions(env, [5, 5, 5, 3, 3, 3, 3, 3, 3], seed=0)  # one up too few: the wall
        assert info["outcome"] == "crash"
    finally:
        env.close()


def test_seeded_runs_are_identical() -> None:
    actions = [6, 0, 5, 3, 7, 2, 4, 1]
    runs = []
    for _ in range(2):
        env = make_env(WORLDS / "random_obstacle.yaml", seed=11)
        try:
            first, _ = run_actions(env, actions, seed=5)
            second, _ = run_actions(env, actions)  # next episode, seed drawn from the env
            runs.append(first + second)
        finally:
            env.close()
    assert len(runs[0]) == len(runs[1])
    for a, b in zip(*runs, strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("estimator", ["sensors", "ground_truth"])
def test_the_fused_direct_loop_flies_exactly_like_the_class_path(estimator: str) -> None:
    """The `direct` backend's fused loop (two compiled calls per vehicle and step) composes the
    components' own kernels: it must match SensorSuite + StubAutopilot + Simulation.step bit for
    bit, over episode starts (takeoff), flight, a crash and a reset."""
    actions = [6, 0, 0, 0, 5, 3, 7, 2]
    runs = []
    for fused in (True, False):
        env = make_env(WORLDS / "obstacle.yaml", seed=3, estimator=estimator)
        backend = env.unwrapped.backend
        backend.fused = fused
        try:
            seen, _ = run_actions(env, actions, seed=3)
            seen += run_actions(env, actions[:3])[0]
            state = backend.sim.state(0)
            seen.append(np.concatenate([state.position_enu_m, state.quaternion_enu_flu, state.rotor_speeds_rad_s,
                                        backend.autopilots[0].estimate.position_ned_m]))
            runs.append(seen)
        finally:
            env.close()
    assert len(runs[0]) == len(runs[1])
    for a, b in zip(*runs, strict=True):
        np.testing.assert_array_equal(a, b)


def test_descents_at_10_hz_fly_exactly_like_the_class_path_and_mostly_compiled(monkeypatch) -> None:  # noqa: ANN001
    """Each descent command makes the land detector suspect a ground contact until the vehicle
    gathers speed (its first stage): those steps run compiled (`steady_output`), and the flight
    is the class path's bit for bit."""
    rng = np.random.default_rng(5)
    actions = [np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), -abs(rng.uniform(0.3, 1))], dtype=np.float32)
               if k % 2 else rng.uniform(-1, 1, 3).astype(np.float32) for k in range(40)]
    calls = [0]
    step = Commander.step

    def counted(self, *args):  # noqa: ANN001, ANN002, ANN202
        calls[0] += 1
        return step(self, *args)

    monkeypatch.setattr(Commander, "step", counted)
    runs, commander_steps = [], []
    for fused in (True, False):
        env = make_env(WORLDS / "obstacle_continuous.yaml", seed=4)
        backend = env.unwrapped.backend
        backend.fused = fused
        calls[0], steps = 0, backend.steps
        try:
            seen, _ = run_actions(env, actions, seed=4)
            state = backend.sim.state(0)
            seen.append(np.concatenate([state.position_enu_m, state.quaternion_enu_flu, state.rotor_speeds_rad_s]))
            runs.append(seen)
            commander_steps.append(calls[0] / (backend.steps - steps))
        finally:
            env.close()
    assert len(runs[0]) == len(runs[1])
    for a, b in zip(*runs, strict=True):
        np.testing.assert_array_equal(a, b)
    # the class path runs the Python commander every step; the fused loop about once a decision
    # (the new setpoint) and when a suspicion starts or ends, not through it (25 steps a decision)
    assert commander_steps[1] == 1.0
    assert commander_steps[0] < 0.08, commander_steps  # 0.14 when suspicions ran in Python


def test_hovering_until_the_step_limit_truncates() -> None:
    env = make_env(WORLDS / "empty.yaml")
    try:
        env.reset(seed=0)
        for step in range(1, env.scenario.task.max_steps + 1):
            _, reward, terminated, truncated, info = env.step(7)
            assert not terminated
            assert truncated == (step == env.scenario.task.max_steps)
        assert info["outcome"] == "timeout" and info["step"] == 20
        assert info["sim_time_s"] >= 20.0
    finally:
        env.close()


NEW_SCENARIO = """
world:
  name: tmp_corridor
  description: A corridor test scenario written by a test, no code.
  workspace: {min: [-3, -2, 0], max: [12, 2, 4]}
  vehicles:
    - name: scout
      model: iris
      spawn: {position: [0, 0, 0.06], yaw: 0, randomize: {position: [0.5, 0.5, 0]}}
      goal: end
  goals:
    - {name: end, center: [8, 0, 1.5], size: [1.5, 1.5, 1.5]}
  obstacles:
    - {name: pillar, shape: cylinder, radius: 0.3, height: 4, position: [4, 1.5, 2]}
task:
  max_steps: 15
  start_altitude_m: 1.5
  action: {speed_m_s: 1.5, duration_s: 0.8, zero_velocity_s: 0.2, frame: goal}
  observation:
    - goal_offset
    - velocity
    - lidar: [horizontal]
    - lidar_flags
    - dummy: 3
  reward:
    closer_to_goal: {scale: 20, mode: binary}
    goal_reached: 1000
    per_step: -10
    crash: -500
    out_of_workspace: -200
"""


def test_a_new_scenario_file_runs_without_code(tmp_path: Path) -> None:
    path = tmp_path / "corridor.yaml"
    path.write_text(NEW_SCENARIO)
    env = make_env(path, seed=3)
    try:
        assert env.observation_space.shape == (3 + 3 + 35 + 2 + 3,)
        assert "`goal_offset`" in env.describe()
        # frame: goal -> action 3 is "forward" = east here; 1.5 m/s for 0.8 s + 0.2 s hover
        obs, info = env.reset()
        outcomes = []
        for _ in range(2):
            _, info = run_actions(env, [3] * 15)
            outcomes.append(info["outcome"])
            assert set(info["reward_terms"]) == {"closer_to_goal", "goal_reached", "per_step",
                                                 "crash", "out_of_workspace"}
        assert outcomes == ["goal", "goal"]
        assert info["sim_time_s"] < 20.0
        # flying up leaves the 4 m high workspace
        _, info = run_actions(env, [5] * 15)
        assert info["outcome"] == "out"
        assert info["reward_terms"]["out_of_workspace"] == -200.0
    finally:
        env.close()


def test_single_env_in_a_two_drone_world_controls_one_drone() -> None:
    env = make_env(WORLDS / "two_drones_empty.yaml", drone=1)
    try:
        _, start = env.reset(seed=0)
        _, info = run_actions(env, [0, 0, 0], seed=0)
        # drone 1 starts at the north end; with the thesis's swap its "east" flies west
        assert start["position_enu_m"][1] > 9.0
        assert info["position_enu_m"][0] < start["position_enu_m"][0] - 2.0
    finally:
        env.close()


def test_bad_arguments_fail_clearly() -> None:
    with pytest.raises(ValueError, match="autopilot must be one of direct, stub, px4"):
        make_env(WORLDS / "empty.yaml", autopilot="gazebo")
    with pytest.raises(ValueError, match="drone must be in 0..0"):
        make_env(WORLDS / "empty.yaml", drone=1)
    env = make_env(WORLDS / "empty.yaml")
    try:
        env.reset(seed=0)
        with pytest.raises(ValueError, match="action must be"):
            env.step(9)
    finally:
        env.close()


def test_module_exports_the_documented_api() -> None:
    for name in ("make_env", "make_parallel_env", "SitlEnv", "SitlParallelEnv", "load_scenario"):
        assert hasattr(envs, name)
    assert "## Action Space" in envs.SitlEnv.__doc__


WALKER_SCENARIO = """
world:
  name: tmp_walker
  description: A walker coming straight at a hovering drone, written by a test.
  workspace: {min: [-10, -3, 0], max: [10, 3, 4]}
  vehicles:
    - {name: scout, model: iris, spawn: {position: [0, 0, 0.06], yaw: 0}, goal: end}
  goals:
    - {name: end, center: [0, 2.5, 1.5], size: [1, 1, 1]}
  obstacles:
    # 1 s of episode start (the settle after the in-air placement) brings it from 5.7 m to 4.7 m,
    # inside the lidar's 5 m
    - {name: walker, shape: cylinder, radius: 0.25, height: 3.5, position: [5.7, 0, 1.75], mass: 70,
       mover: {type: patrol, speed: 1.0, points: [[5.7, 0, 1.75], [1.5, 0, 1.75]]}}
task:
  max_steps: 5
  start_altitude_m: 1.5
  action: {speed_m_s: 1.0, duration_s: 1.0, frame: world}
  observation:
    - lidar: [horizontal]
    - lidar_change: [horizontal]
  reward: {per_step: -1}
"""


def test_lidar_change_shows_a_walker_coming_closer(tmp_path: Path) -> None:
    path = tmp_path / "walker.yaml"
    path.write_text(WALKER_SCENARIO)
    env = make_env(path, seed=0)
    try:
        layout = observation_layout(env.scenario.task.observation)
        obs, _ = env.reset(seed=0)
        assert np.all(obs[layout["lidar_change"]] == 0.0)  # nothing seen moving yet
        east = int(np.argmin(obs[layout["lidar"]]))         # the ray that sees the walker
        before = obs[layout["lidar"]]
        obs, *_ = env.step(7)                               # hover while it walks 1 m closer
        change = obs[layout["lidar_change"]]
        assert np.allclose(change, obs[layout["lidar"]] - before, atol=1e-5)
        assert change[east] == pytest.approx(-1.0, abs=0.15)
        assert np.all(np.abs(np.delete(change, east)) < np.abs(change[east]))
    finally:
        env.close()
