"""Continuous velocity actions (`task.action.type: velocity`) on the real simulator: the shipped
`*_continuous.yaml` scenarios pass Gymnasium's, PettingZoo's and SB3's env checkers, `direct`
and `stub` fly the same continuous setpoints alike, the loader refuses bad settings in one line,
and the per-second reward terms give the same return for the same flight at 1 s and 0.1 s."""

from __future__ import annotations

import math
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import yaml

from sitl_bridge.envs import load_scenario, make_env, make_parallel_env
from sitl_bridge.errors import ConfigError
from sitl_bridge.frames import quat_to_euler, wrap_pi

WORLDS = Path(__file__).resolve().parents[1] / "worlds"
SINGLE = ["obstacle_continuous.yaml", "random_obstacle_continuous.yaml", "window_continuous.yaml"]
MULTI = "two_drones_empty_relative_continuous.yaml"


def variant(tmp_path: Path, source: str, name: str = "variant.yaml", **task: object) -> Path:
    """A copy of a shipped scenario with `task:` keys replaced (`action`, `reward`, ...)."""
    data = yaml.safe_load((WORLDS / source).read_text())
    for key, value in task.items():
        if value is None:
            data["task"].pop(key, None)
        else:
            data["task"][key] = value
    data.pop("train", None)
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return path


# -- the env checkers -------------------------------------------------------------------------
@pytest.mark.parametrize("filename", [*SINGLE, MULTI])
def test_gymnasium_and_sb3_env_checkers_pass_on_every_shipped_continuous_scenario(filename: str) -> None:
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env = make_env(WORLDS / filename, seed=0)
    try:
        space = env.action_space
        assert isinstance(space, gym.spaces.Box) and space.shape == (3,) and space.dtype == np.float32
        assert np.all(space.low == -1.0) and np.all(space.high == 1.0)
        assert env.scenario.task.action.duration_s == 0.1
        check_env(env, skip_render_check=True)
        sb3_check_env(env, warn=True)
    finally:
        env.close()


def test_pettingzoo_parallel_api_test_passes_on_the_continuous_two_drone_scenario() -> None:
    from pettingzoo.test import parallel_api_test

    env = make_parallel_env(WORLDS / MULTI, seed=0)
    try:
        for agent in env.possible_agents:
            assert env.action_space(agent) == gym.spaces.Box(-1.0, 1.0, (3,), np.float32)
        parallel_api_test(env, num_cycles=30)
    finally:
        env.close()


# -- what an action flies -----------------------------------------------------------------------
def _fly(env, actions: list[np.ndarray], seed: int) -> tuple[list[np.ndarray], list[float]]:
    """Positions and true headings (ENU yaw) after reset and after every action."""
    _, info = env.reset(seed=seed)
    positions, yaws = [info["position_enu_m"]], [_yaw(env)]
    for action in actions:
        _, _, terminated, truncated, info = env.step(action)
        positions.append(info["position_enu_m"])
        yaws.append(_yaw(env))
        if terminated or truncated:
            break
    return positions, yaws


def _yaw(env) -> float:
    return float(quat_to_euler(env.runner.snapshot.states[env.drone].quaternion_enu_flu)[2])


def _script(size: int) -> list[np.ndarray]:
    """2 s up, 2 s north, 1 s diagonal down-north-east (beyond the unit ball: capped), 1 s hover
    (in O: over the block and down into the goal)."""
    plan = [(0.0, 0.0, 0.5)] * 20 + [(0.0, 1.0, 0.0)] * 20 + [(1.0, 1.0, -1.0)] * 10 + [(0.0, 0.0, 0.0)] * 10
    return [np.array([*v, 0.0][:size] if size == 3 else [*v, 1.0], dtype=np.float32) for v in plan]


def test_direct_and_stub_fly_the_same_continuous_setpoints(free_instance: int) -> None:
    script = _script(3)
    direct = make_env(WORLDS / "obstacle_continuous.yaml", autopilot="direct")
    try:
        expected, _ = _fly(direct, script, seed=2)
    finally:
        direct.close()
    assert len(expected) > 45  # over the block and down into the goal region (ends the episode)
    assert expected[20][2] - expected[0][2] == pytest.approx(2.0, abs=0.3)  # 0.5 x 2 m/s for 2 s
    stub = make_env(WORLDS / "obstacle_continuous.yaml", autopilot="stub", speed_factor=0.0,
                    instance_base=free_instance)
    try:
        got, _ = _fly(stub, script, seed=2)
        # both end in the goal region; positions 0.1 m apart may cross its edge one 0.1 s decision apart
        assert abs(len(got) - len(expected)) <= 1
        for step, (a, b) in enumerate(zip(expected, got, strict=False)):
            assert np.linalg.norm(a - b) < 0.1, (step, a, b)
    finally:
        stub.close()


def test_yaw_rate_turns_the_heading_alike_on_direct_and_stub(tmp_path: Path, free_instance: int) -> None:
    """`yaw: rate` with `frame: body`: a full left-turn command for 3 s turns the heading by
    3 x 45 deg on both backends, "forward" then flies along the new heading, the new heading reaching the stub even where the velocity stays
    the same (the delivery check waits for it)."""
    path = variant(tmp_path, "obstacle_continuous.yaml", action={
        "type": "velocity", "max_speed_m_s": 2.0, "duration_s": 0.1, "frame": "body", "yaw": "rate"})
    script = [np.array([0.0, 0.0, 0.0, 1.0], dtype=np.float32)] * 30 + \
             [np.array([0.0, 0.0, 0.0, 0.0], dtype=np.float32)] * 10 + \
             [np.array([0.0, 0.5, 0.0, 0.0], dtype=np.float32)] * 10  # then forward, along the nose
    direct = make_env(path, autopilot="direct")
    try:
        assert direct.action_space.shape == (4,)
        positions, yaws = _fly(direct, script, seed=2)
    finally:
        direct.close()
    turned = math.degrees(wrap_pi(yaws[-1] - yaws[0]))
    assert turned == pytest.approx(135.0, abs=5.0)
    forward = positions[-1] - positions[40]
    assert math.degrees(wrap_pi(math.atan2(forward[1], forward[0]) - yaws[40])) == pytest.approx(0.0, abs=5.0)
    stub = make_env(path, autopilot="stub", speed_factor=0.0, instance_base=free_instance)
    try:
        got, got_yaws = _fly(stub, script, seed=2)
        for step, (a, b) in enumerate(zip(positions, got, strict=True)):
            assert np.linalg.norm(a - b) < 0.1, (step, a, b)
        assert math.degrees(wrap_pi(got_yaws[-1] - got_yaws[0])) == pytest.approx(turned, abs=3.0)
    finally:
        stub.close()


def test_the_speed_is_capped_by_the_norm_and_bad_actions_are_refused() -> None:
    env = make_env(WORLDS / "obstacle_continuous.yaml", seed=0)
    try:
        env.reset(seed=0)
        runner = env.runner
        _, _, _, _, info = env.step(np.array([3.0, -7.0, 0.0], dtype=np.float32))
        assert info["action"] == [1.0, -1.0, 0.0]  # clipped per component first
        # ... then the norm capped: 2 m/s along (1, -1), not 2.83 m/s
        assert np.linalg.norm(runner.backend._velocities[0]) == pytest.approx(2.0)
        before = env.runner.step_count
        for bad in (np.array([np.nan, 0, 0]), np.array([0, np.inf, 0]), np.array([0.0, 0.0]), "up"):
            with pytest.raises(ValueError) as error:
                env.step(bad)
            assert "\n" not in str(error.value)
        assert env.runner.step_count == before  # nothing flew
    finally:
        env.close()


def test_goal_frame_is_the_same_manoeuvre_for_both_head_on_drones() -> None:
    env = make_parallel_env(WORLDS / MULTI, seed=0)
    try:
        _, infos = env.reset(seed=0)
        starts = {a: infos[a]["position_enu_m"] for a in env.agents}
        for _ in range(10):
            _, _, _, _, infos = env.step({a: np.array([0.0, 1.0, 0.0], dtype=np.float32) for a in env.agents})
        along, across = [], []
        for agent in env.possible_agents:
            moved = infos[agent]["position_enu_m"] - starts[agent]
            toward = infos[agent]["goal_enu_m"] - starts[agent]
            toward[2] = 0.0
            toward /= np.linalg.norm(toward)
            along.append(float(np.dot(moved, toward)))
            across.append(float(np.linalg.norm(moved - along[-1] * toward)))
        # 1 s of "forward" from a hover: each flew about a metre toward its own goal, alike
        assert min(along) > 0.7 and abs(along[0] - along[1]) < 0.05, along
        assert max(across) < 0.1, across
    finally:
        env.close()


# -- the loader ---------------------------------------------------------------------------------
@pytest.mark.parametrize(("action", "key"), [
    ({"type": "velocity", "duration_s": 0.005}, "duration_s"),        # not a whole 4 ms step
    ({"type": "velocity", "duration_s": 0.0}, "task.action.duration_s"),
    ({"type": "velocity", "frame": "nose"}, "task.action.frame"),
    ({"type": "velocity", "max_speed_m_s": 0}, "task.action.max_speed_m_s"),
    ({"type": "velocity", "max_speed_m_s": -2}, "task.action.max_speed_m_s"),
    ({"type": "velocity", "max_speed_m_s": 500}, "task.action.max_speed_m_s"),
    ({"type": "velocity", "max_speed_m_s": ".inf"}, "task.action.max_speed_m_s"),
    ({"type": "velocity", "yaw": "spin"}, "task.action.yaw"),
    ({"type": "velocity", "speed_m_s": 1.0}, "task.action.speed_m_s"),
    ({"type": "velocity", "swap_drones": [0]}, "task.action.swap_drones"),
    ({"type": "joystick"}, "task.action.type"),
    ({"max_speed_m_s": 2.0}, "task.action.max_speed_m_s"),           # discrete has no max speed
    ({"frame": "body"}, "task.action.frame"),                        # body is for velocity actions
])
def test_loader_refuses_bad_continuous_settings_in_one_line(tmp_path: Path, action: dict, key: str) -> None:
    path = variant(tmp_path, "obstacle_continuous.yaml", action=action)
    with pytest.raises(ConfigError) as error:
        load_scenario(path)
    message = str(error.value)
    assert "\n" not in message and message.startswith(str(path)) and key in message, message


def test_loader_refuses_both_episode_limits_and_smoothness_on_discrete(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="max_steps or max_time_s"):
        load_scenario(variant(tmp_path, "obstacle_continuous.yaml", max_steps=45))
    with pytest.raises(ConfigError, match="task.reward.smoothness: only with"):
        load_scenario(variant(tmp_path, "obstacle.yaml", reward={"per_step": -5, "smoothness": -1}))


def test_an_episode_limit_in_seconds_means_the_same_flight_time_at_any_rate(tmp_path: Path) -> None:
    fast = load_scenario(WORLDS / "obstacle_continuous.yaml").task
    assert (fast.max_time_s, fast.max_steps) == (45.0, 450)
    slow = load_scenario(variant(tmp_path, "obstacle_continuous.yaml", action={
        "type": "velocity", "duration_s": 1.0})).task
    assert (slow.max_time_s, slow.max_steps) == (45.0, 45)
    odd = load_scenario(variant(tmp_path, "obstacle_continuous.yaml", max_time_s=0.95)).task
    assert odd.max_steps == 10  # rounded up: the decision that reaches it ends the episode


# -- rewards at any decision rate ---------------------------------------------------------------
def _straight_return(path: Path, seconds: float) -> tuple[float, np.ndarray, dict[str, float]]:
    env = make_env(path, seed=0)
    try:
        env.reset(seed=0)
        period = env.scenario.task.action.duration_s
        total, terms = 0.0, {}
        for _ in range(round(seconds / period)):
            _, reward, terminated, truncated, info = env.step(np.array([0.0, 0.5, 0.0], dtype=np.float32))
            total += reward
            for name, value in info["reward_terms"].items():
                terms[name] = terms.get(name, 0.0) + value
            assert not (terminated or truncated)
        return total, info["position_enu_m"], terms
    finally:
        env.close()


def test_the_same_straight_flight_earns_the_same_return_at_1_s_and_0_1_s_decisions(tmp_path: Path) -> None:
    reward = {"closer_to_goal": 10, "per_step": -5, "near_obstacle": -10, "crash": -100}
    action = {"type": "velocity", "max_speed_m_s": 2.0, "frame": "world"}
    every_second = variant(tmp_path, "random_obstacle_continuous.yaml", "one.yaml", reward=reward,
                           action={**action, "duration_s": 1.0})
    ten_hertz = variant(tmp_path, "random_obstacle_continuous.yaml", "ten.yaml", reward=reward,
                        action={**action, "duration_s": 0.1})
    slow, slow_end, slow_terms = _straight_return(every_second, 3.0)    # 3 decisions
    fast, fast_end, fast_terms = _straight_return(ten_hertz, 3.0)       # 30 decisions
    assert np.linalg.norm(slow_end - fast_end) < 0.05  # the same flight ...
    assert slow_terms["per_step"] == pytest.approx(-15.0) and fast_terms["per_step"] == pytest.approx(-15.0)
    assert fast == pytest.approx(slow, abs=1.0)  # ... the same return (unscaled: -15 vs -150 per_step)


def test_a_discrete_scenario_keeps_its_space_and_per_step_reward(tmp_path: Path) -> None:
    env = make_env(WORLDS / "obstacle.yaml", seed=0)
    try:
        assert env.action_space == gym.spaces.Discrete(8)
        assert env.scenario.task.action.type == "discrete" and env.scenario.task.max_time_s is None
        env.reset(seed=0)
        _, _, _, _, info = env.step(7)  # hover 1 s: the thesis's -5 per step
        assert info["reward_terms"]["per_step"] == -5.0 and info["action"] == 7
    finally:
        env.close()
    half = load_scenario(variant(tmp_path, "obstacle.yaml", action={"speed_m_s": 1.0, "duration_s": 0.5}))
    assert {t.name: t.step_scale for t in half.task.rewards}["per_step"] == -2.5  # per second of flight


def test_smoothness_charges_the_change_of_the_normalised_action(tmp_path: Path) -> None:
    path = variant(tmp_path, "obstacle_continuous.yaml", reward={"per_step": 0, "smoothness": -2})
    env = make_env(path, seed=0)
    try:
        env.reset(seed=0)
        got = []
        for action in ([1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 5.0, 0.0]):
            _, _, _, _, info = env.step(np.array(action, dtype=np.float32))
            got.append(info["reward_terms"]["smoothness"])
        assert got == pytest.approx([0.0, 0.0, -2.0 * math.sqrt(2.0), 0.0])  # 5 is clipped to 1
        env.reset(seed=0)
        _, _, _, _, info = env.step(np.array([0.0, -1.0, 0.0], dtype=np.float32))
        assert info["reward_terms"]["smoothness"] == 0.0  # a new episode starts afresh
    finally:
        env.close()
