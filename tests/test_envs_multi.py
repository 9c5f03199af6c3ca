"""Multi-drone learning inputs on the direct simulator: agent-relative
features in the own travel frame, the separation reward, and an explicit priority that follows
its rule, not the drone id."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from sitl_bridge.envs import make_parallel_env
from sitl_bridge.envs.features import travel_frame
from sitl_bridge.envs.priority import priorities
from sitl_bridge.envs.scenario import load_scenario

WORLDS = Path(__file__).resolve().parents[1] / "worlds"


def _write(tmp_path: Path, base: str, edit) -> Path:
    root = yaml.safe_load((WORLDS / base).read_text())
    edit(root)
    path = tmp_path / base
    path.write_text(yaml.safe_dump(root, sort_keys=False))
    return path


def _features(path: Path, seed: int = 0, actions: dict[str, int] | None = None) -> dict[str, dict[str, np.ndarray]]:
    """Each drone's observation split by feature, after reset (and one step of `actions`)."""
    scenario = load_scenario(path)
    env = make_parallel_env(path, seed=seed)
    try:
        observations, _ = env.reset(seed=seed)
        if actions:
            observations, *_ = env.step(actions)
    finally:
        env.close()
    out = {}
    for agent, obs in observations.items():
        parts, index = {}, 0
        for f in scenario.task.observation:
            parts[f.name] = np.asarray(obs[index:index + f.size])
            index += f.size
        out[agent] = parts
    return out


def test_travel_frame_axes() -> None:
    rotation = travel_frame(np.zeros(3), np.array([0.0, 10.0, 0.0]))  # goal north
    assert rotation @ np.array([1.0, 0, 0]) == pytest.approx([1, 0, 0])  # east is right
    rotation = travel_frame(np.array([0.0, 10.0, 0.0]), np.zeros(3))  # goal south
    assert rotation @ np.array([1.0, 0, 0]) == pytest.approx([-1, 0, 0])  # east is left
    assert rotation @ np.array([0, -1.0, 0]) == pytest.approx([0, 1, 0])  # south is forward


def test_head_on_drones_see_mirror_situations_as_the_same_numbers(tmp_path: Path) -> None:
    def edit(root: dict) -> None:
        root["task"]["action"] = {"frame": "goal"}
        root["task"]["observation"] = ["travel_goal_offset", "travel_velocity", "travel_others"]

    path = _write(tmp_path, "two_drones_empty.yaml", edit)
    # Both fly "right" of their travel direction: drone0 east, drone1 west.
    seen = _features(path, actions={"drone0": 0, "drone1": 0})
    a, b = seen["drone0"], seen["drone1"]
    # Horizontal parts equal up to each drone's own flight error (a few cm, measured); a
    # world-frame feature would differ in sign by metres. Heights differ by the drones' hover
    # error after take-off (~0.08 m), so the relative heights are opposite, not equal.
    for name in ("travel_goal_offset", "travel_velocity"):
        assert a[name][:2] == pytest.approx(b[name][:2], abs=0.05), name
    horizontal = [0, 1, 3, 4]
    assert a["travel_others"][horizontal] == pytest.approx(b["travel_others"][horizontal], abs=0.05)
    assert a["travel_others"][[2, 5]] == pytest.approx(-b["travel_others"][[2, 5]], abs=1e-4)
    assert a["travel_goal_offset"][1] > 7.0  # the goal is ahead
    assert a["travel_velocity"][0] > 0.5  # moving right
    assert a["travel_others"][1] > 7.0  # the other drone is ahead ...
    assert a["travel_others"][0] < -0.5  # ... and, both having moved right, to its left


def test_separation_reward_grows_as_the_drones_close_in(tmp_path: Path) -> None:
    def edit(root: dict) -> None:
        root["task"]["reward"] = {"separation": {"scale": -10, "distance_m": 9.5}}
        root["task"]["action"] = {"frame": "goal"}

    env = make_parallel_env(_write(tmp_path, "two_drones_empty.yaml", edit), seed=0)
    try:
        env.reset(seed=0)
        penalties = []
        for _ in range(3):  # both fly forward: head-on, closing 2 m per step
            _, rewards, *_ = env.step({"drone0": 3, "drone1": 3})
            penalties.append(rewards["drone0"])
    finally:
        env.close()
    assert penalties[0] < 0 and penalties[2] < penalties[1] < penalties[0]
    # 10 m apart minus about 2 m per step: -10 * (1 - d / 9.5)
    assert penalties[2] == pytest.approx(-10 * (1 - 4.0 / 9.5), abs=1.5)


def test_give_way_separation_is_paid_only_by_the_drone_without_right_of_way(tmp_path: Path) -> None:
    def edit(root: dict) -> None:
        root["task"]["reward"] = {"separation": {"scale": -10, "distance_m": 9.5, "give_way": True}}
        root["task"]["action"] = {"frame": "goal"}
        root["task"]["priority"] = "lower_coordinate_yields"

    env = make_parallel_env(_write(tmp_path, "two_drones_empty.yaml", edit), seed=0)
    try:
        env.reset(seed=0)
        for _ in range(3):  # head-on, closing 2 m per step
            _, rewards, *_ = env.step({"drone0": 3, "drone1": 3})
    finally:
        env.close()
    # drone0 starts further south: it yields and pays the full term; drone1 has right of way
    assert rewards["drone0"] == pytest.approx(-10 * (1 - 4.0 / 9.5), abs=1.5)
    assert rewards["drone1"] == 0.0


@pytest.mark.parametrize("rule", ["lower_coordinate_yields", "first_to_arrive"])
def test_priority_follows_the_rule_not_the_drone_id_when_spawns_swap(tmp_path: Path, rule: str) -> None:
    def edit(swap: bool, shift_goal: bool):
        def apply(root: dict) -> None:
            root["task"]["priority"] = rule
            root["task"]["observation"] = ["own_priority", "other_priority", "own_id"]
            vehicles = root["world"]["vehicles"]
            if shift_goal:  # first_to_arrive needs unequal distances: drone at y=-4 has a nearer goal
                root["world"]["goals"][0]["center"] = [0, 2, 5.0]
            if swap:
                vehicles[0]["spawn"], vehicles[1]["spawn"] = vehicles[1]["spawn"], vehicles[0]["spawn"]
                vehicles[0]["goal"], vehicles[1]["goal"] = vehicles[1]["goal"], vehicles[0]["goal"]
        return apply

    shift = rule == "first_to_arrive"
    plain = _features(_write(tmp_path / "a", "two_drones_window.yaml", edit(False, shift)) if
                      (tmp_path / "a").mkdir() is None else None)
    swapped = _features(_write(tmp_path / "b", "two_drones_window.yaml", edit(True, shift)) if
                        (tmp_path / "b").mkdir() is None else None)
    # Plain: drone0 starts south (y=-4) -> lower coordinate -> yields (0) under the thesis rule;
    # under first_to_arrive drone0's goal is 6 m away, drone1's 8 m -> drone0 goes first (1).
    expected_drone0 = 0.0 if rule == "lower_coordinate_yields" else 1.0
    assert plain["drone0"]["own_priority"] == pytest.approx([expected_drone0])
    assert plain["drone1"]["own_priority"] == pytest.approx([1 - expected_drone0])
    # Swapped spawns and goals: the priority moves with the situation, not with the id.
    assert swapped["drone1"]["own_priority"] == pytest.approx([expected_drone0])
    assert swapped["drone0"]["own_priority"] == pytest.approx([1 - expected_drone0])
    assert swapped["drone0"]["other_priority"] == pytest.approx([expected_drone0])
    assert swapped["drone0"]["own_id"] == plain["drone0"]["own_id"] == pytest.approx([0.0])


def test_priority_rules_directly() -> None:
    starts = [np.array([0.0, 5, 0]), np.array([3.0, -1, 0]), np.array([-2.0, -1, 0])]
    goals = [np.array([0.0, 0, 0]), np.array([0.0, 9, 0]), np.array([0.0, 1, 0])]
    assert priorities("lower_coordinate_yields", starts, starts, goals).tolist() == [1.0, 0.5, 0.0]
    # remaining distances 5, 10.4, 2.8: nearest to its goal first
    assert priorities("first_to_arrive", starts, starts, goals).tolist() == [0.5, 0.0, 1.0]


def test_unknown_priority_rule_is_one_line(tmp_path: Path) -> None:
    from sitl_bridge.errors import ConfigError

    path = _write(tmp_path, "two_drones_window.yaml", lambda r: r["task"].update(priority="id"))
    with pytest.raises(ConfigError, match=r"two_drones_window.yaml: task.priority: expected one of"):
        load_scenario(path)
