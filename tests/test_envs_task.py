"""The `task:` schema, observation features, reward terms and action mapping (no simulation)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from sitl_bridge.envs import load_scenario
from sitl_bridge.envs.actions import action_velocity
from sitl_bridge.envs.features import distance_from_line
from sitl_bridge.envs.rewards import parse_rewards
from sitl_bridge.envs.task import ActionConfig
from sitl_bridge.envs.view import DroneView
from sitl_bridge.errors import ConfigError, Node

WORLDS = Path(__file__).resolve().parents[1] / "worlds"
SCENARIOS = sorted(WORLDS.glob("*.yaml"))

THESIS_STEPS = {"empty": 20, "random_goal": 35, "obstacle": 45, "two_drones_empty": 25, "window": 30}


@pytest.mark.parametrize("path", SCENARIOS, ids=lambda p: p.stem)
def test_every_shipped_scenario_parses(path: Path) -> None:
    scenario = load_scenario(path)
    assert scenario.task.observation_size > 0
    assert scenario.task.rewards
    if path.stem in THESIS_STEPS:
        assert scenario.task.max_steps == THESIS_STEPS[path.stem]


def test_window_and_two_drones_window_have_equal_input_sizes() -> None:
    # the dummy padding exists so W -> TW transfer keeps the network's input size
    assert load_scenario(WORLDS / "window.yaml").task.observation_size == \
        load_scenario(WORLDS / "two_drones_window.yaml").task.observation_size


def test_thesis_reward_ratios_not_huge() -> None:
    for path in SCENARIOS:
        scales = {t.name: t.scale for t in load_scenario(path).task.rewards}
        assert scales["crash"] < 0 and abs(scales["crash"]) <= scales["goal_reached"]
        assert scales["per_step"] < 0


def _broken(tmp_path: Path, task_yaml: str) -> Path:
    text = (WORLDS / "empty.yaml").read_text()
    head = text[: text.index("\ntask:")]
    path = tmp_path / "broken.yaml"
    path.write_text(head + "\ntask:\n" + task_yaml)
    return path


@pytest.mark.parametrize(("task_yaml", "message"), [
    ("  max_steps: 10\n  observation: [positon]\n  reward: {per_step: -1}\n",
     "task.observation[0]: unknown observation feature 'positon'"),
    ("  max_steps: 10\n  observation: [position]\n  reward: {crash: -1e12}\n",
     "task.reward.crash: expected a number >= -100000.0 <= 100000.0"),
    ("  max_steps: ten\n  observation: [position]\n  reward: {per_step: -1}\n",
     "task.max_steps: expected an integer >= 1"),
    ("  max_steps: 10\n  observation: [{lidar: [sideways]}]\n  reward: {per_step: -1}\n",
     "task.observation[0].lidar[0]: expected one of horizontal, up, down"),
    ("  max_steps: 10\n  observation: [position]\n  reward: {per_stp: -1}\n",
     "task.reward.per_stp: unknown reward term"),
    ("  max_steps: 10\n  action: {frame: body}\n  observation: [position]\n  reward: {per_step: -1}\n",
     "task.action.frame: expected one of world, goal"),
    ("  max_steps: 10\n  observation: [position]\n",
     "task.reward: required key is missing"),
    ("  max_steps: 10\n  sise: 3\n  observation: [position]\n  reward: {per_step: -1}\n",
     "task.sise: unknown key"),
])
def test_bad_task_is_one_line_naming_file_and_key(tmp_path: Path, task_yaml: str, message: str) -> None:
    path = _broken(tmp_path, task_yaml)
    with pytest.raises(ConfigError) as info:
        load_scenario(path)
    text = str(info.value)
    assert "\n" not in text
    assert text.startswith(f"{path}: ")
    assert message in text


def _view(position, previous, goal=(0.0, 10.0, 2.5), **flags) -> DroneView:
    return DroneView(
        index=0, position_enu_m=np.array(position, float), previous_position_enu_m=np.array(previous, float),
        euler_enu_rad=np.zeros(3), velocity_enu_m_s=np.zeros(3), start_enu_m=np.array([0.0, 0.0, 2.5]),
        goal_enu_m=np.array(goal, float), lidar={"horizontal": np.full(35, 5.0), "up": np.full(6, 5.0),
                                                 "down": np.full(6, 5.0)},
        priority=1.0, other_priorities=np.zeros(0), others_position_enu_m=np.zeros((0, 3)),
        others_velocity_enu_m_s=np.zeros((0, 3)), **flags)


def test_reward_terms_each_scaled_by_name() -> None:
    terms = parse_rewards(Node({"closer_to_goal": 10, "goal_reached": 500, "per_step": -5,
                                "near_obstacle": -10, "crash": -100}, "t.yaml", "task.reward"))
    moved = _view((0, 1, 2.5), (0, 0, 2.5), near_obstacle=True)
    values = {t.name: t(moved) for t in terms}
    assert values == pytest.approx({"closer_to_goal": 10.0, "goal_reached": 0.0, "per_step": -5.0,
                                    "near_obstacle": -10.0, "crash": 0.0})
    crashed = {t.name: t(_view((0, 0, 2.5), (0, 1, 2.5), crashed=True, near_obstacle=True)) for t in terms}
    assert crashed["crash"] == -100.0 and crashed["near_obstacle"] == 0.0
    assert crashed["closer_to_goal"] == pytest.approx(-10.0)  # moving away costs


def test_binary_closer_term() -> None:
    (term,) = parse_rewards(Node({"closer_to_goal": {"scale": 15, "mode": "binary"}}, "t.yaml", "task.reward"))
    assert term(_view((0, 1, 2.5), (0, 0, 2.5))) == 15.0
    assert term(_view((0, 0.05, 2.5), (0, 0, 2.5))) == 0.0
    assert term(_view((0, 0, 2.5), (0, 1, 2.5))) == 0.0


def _velocity(action: int, config: ActionConfig, drone: int = 0, goal=(0.0, 10.0, 2.5),
              position=(0.0, 0.0, 2.5)) -> np.ndarray:
    return action_velocity(action, config=config, drone=drone, position_enu_m=np.array(position),
                           start_enu_m=np.array([0.0, 0.0, 2.5]), goal_enu_m=np.array(goal))


def test_world_frame_actions_follow_the_thesis_table() -> None:
    config = ActionConfig()
    expected_ned = {0: (0, 1, 0), 1: (0, -1, 0), 2: (-1, 0, 0), 3: (1, 0, 0), 4: (0, 0, 1),
                    5: (0, 0, -1), 6: (1, 0, 0), 7: (0, 0, 0)}
    for action, ned in expected_ned.items():
        assert _velocity(action, config) == pytest.approx(np.array(ned, float)), action
    with pytest.raises(ValueError):
        _velocity(8, config)


def test_swapped_drone_mirrors_horizontal_actions() -> None:
    config = ActionConfig(swap_drones=(1,))
    assert _velocity(3, config, drone=1) == pytest.approx([-1.0, 0.0, 0.0])   # "north" flies south
    assert _velocity(0, config, drone=1) == pytest.approx([0.0, -1.0, 0.0])   # "east" flies west
    assert _velocity(5, config, drone=1) == pytest.approx([0.0, 0.0, -1.0])   # vertical unchanged
    assert _velocity(3, config, drone=0) == pytest.approx([1.0, 0.0, 0.0])


def test_goal_frame_turns_with_the_start_goal_direction() -> None:
    config = ActionConfig(frame="goal")
    # goal due east of the start: forward = east, right = south
    east_goal = (10.0, 0.0, 2.5)
    assert _velocity(3, config, goal=east_goal) == pytest.approx([0.0, 1.0, 0.0], abs=1e-12)
    assert _velocity(0, config, goal=east_goal) == pytest.approx([-1.0, 0.0, 0.0], abs=1e-12)
    # goal due north: same as the world frame
    assert _velocity(0, config) == pytest.approx([0.0, 1.0, 0.0], abs=1e-12)


def test_toward_goal_slows_down_to_stop_at_the_goal() -> None:
    config = ActionConfig()
    v = _velocity(6, config, goal=(0.0, 0.4, 2.5))
    assert np.linalg.norm(v) == pytest.approx(0.4)
    v = _velocity(6, config, goal=(3.0, 4.0, 2.5))
    assert v == pytest.approx([0.8, 0.6, 0.0])


def test_distance_from_line() -> None:
    a, b = np.array([0.0, 0.0, 0.0]), np.array([0.0, 10.0, 0.0])
    assert distance_from_line(np.array([3.0, 5.0, 4.0]), a, b) == pytest.approx(5.0)
    assert distance_from_line(np.array([3.0, 4.0, 0.0]), a, a) == pytest.approx(5.0)
    assert math.isfinite(distance_from_line(np.array([1e9, 0, 0]), a, b))


@pytest.mark.parametrize("path", SCENARIOS, ids=lambda p: p.stem)
def test_every_scenario_has_a_manual(path: Path) -> None:
    from sitl_bridge.envs.manual import describe

    scenario = load_scenario(path)
    text = describe(scenario)
    assert f"# {scenario.name}" in text
    for feature in scenario.task.observation:
        assert f"`{feature.name}`" in text
    assert f"after {scenario.task.max_steps} steps" in text
