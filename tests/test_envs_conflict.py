"""Multi-drone episode ends (TW): `end.after_goal` (a drone at its goal hovers or
lands), `end.conflict_blame` (a crash between drones charged to both, or only to the drone
that must give way) and `end.min_separation_m` (closer than that is a conflict crash). Real direct-backend flights in the TW-relative scenario."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from sitl_bridge.envs import make_parallel_env, worlds_dir
from sitl_bridge.errors import ConfigError

WORLD = worlds_dir() / "two_drones_window_relative.yaml"
CLIMB, FORWARD, TOWARD_GOAL, HOVER = 5, 3, 6, 7


def _world(tmp_path: Path, **end: object) -> Path:
    data = yaml.safe_load(WORLD.read_text())
    data["task"]["end"].update(end)
    path = tmp_path / "tw.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _fly(path: Path, plan) -> list[dict]:
    """Fly `plan(step) -> action` for both drones until the episode ends; every step's results."""
    env = make_parallel_env(str(path), seed=0)
    try:
        env.reset(seed=0)
        steps = []
        while env.agents and len(steps) < 40:
            _, rewards, terminated, truncated, infos = env.step({a: plan(len(steps)) for a in env.agents})
            steps.append({a: (rewards[a], terminated[a], truncated[a], infos[a]) for a in rewards})
        return steps
    finally:
        env.close()


def _head_on_in_the_window(step: int) -> int:
    return CLIMB if step < 4 else FORWARD  # both climb to the window, then meet in it


def test_give_way_charges_the_drone_without_right_of_way_for_a_crash_between_drones(tmp_path: Path) -> None:
    last = _fly(_world(tmp_path, conflict_blame="give_way"), _head_on_in_the_window)[-1]
    # drone0 starts further south: it must give way (lower_coordinate_yields)
    reward0, terminated0, truncated0, info0 = last["drone0"]
    reward1, terminated1, truncated1, info1 = last["drone1"]
    assert info0["outcome"] == info1["outcome"] == "crash"  # both stop: the episode failed
    assert terminated0 and not truncated0 and info0["reward_terms"]["crash"] == -100
    # the drone with right of way is stopped but not charged: no crash reward, no terminal state
    assert truncated1 and not terminated1 and info1["reward_terms"]["crash"] == 0
    assert reward1 > reward0 + 90


def test_both_drones_are_charged_under_both(tmp_path: Path) -> None:
    last = _fly(_world(tmp_path, conflict_blame="both"), _head_on_in_the_window)[-1]
    for drone in ("drone0", "drone1"):
        _, terminated, truncated, info = last[drone]
        assert info["outcome"] == "crash" and terminated and not truncated
        assert info["reward_terms"]["crash"] == -100


def test_loss_of_separation_is_a_conflict_charged_to_the_drone_that_must_give_way(tmp_path: Path) -> None:
    touching = _fly(_world(tmp_path, conflict_blame="give_way"), _head_on_in_the_window)
    apart = _fly(_world(tmp_path, conflict_blame="give_way", min_separation_m=3.0), _head_on_in_the_window)
    assert len(apart) < len(touching)  # it ends before the drones meet in the window
    _, terminated0, _, info0 = apart[-1]["drone0"]
    _, terminated1, truncated1, info1 = apart[-1]["drone1"]
    assert info0["outcome"] == info1["outcome"] == "crash"
    assert terminated0 and info0["reward_terms"]["crash"] == -100
    assert truncated1 and not terminated1 and info1["reward_terms"]["crash"] == 0


def test_a_wall_crash_next_to_the_other_drone_is_charged_to_both(tmp_path: Path) -> None:
    # toward the goal from 1 m up: both fly into the wall below the window, side by side
    last = _fly(_world(tmp_path, conflict_blame="give_way"), lambda step: TOWARD_GOAL)[-1]
    for drone in ("drone0", "drone1"):
        _, terminated, _, info = last[drone]
        assert info["outcome"] == "crash" and terminated and info["reward_terms"]["crash"] == -100


def test_a_drone_at_its_goal_lands_with_after_goal_land(tmp_path: Path) -> None:
    heights = {}
    for after in ("hover", "land"):
        path = _world(tmp_path, after_goal=after)
        env = make_parallel_env(str(path), seed=0)
        try:
            env.reset(seed=0)
            # drone1 climbs and flies through the window to its goal; drone0 hovers at its spawn
            script = [CLIMB] * 4 + [FORWARD] * 8
            outcome, track = None, []
            for step in range(len(script) + 4):
                actions = {a: (script[step] if a == "drone1" and step < len(script) else HOVER)
                           for a in env.agents}
                _, _, _, _, infos = env.step(actions)
                outcome = infos.get("drone1", {}).get("outcome") or outcome
                track.append(env.runner.snapshot.states[1].position_enu_m[2])
            assert outcome == "goal"
            heights[after] = track[-1]
        finally:
            env.close()
    assert heights["hover"] > 4.0  # it stays in its goal box (4-6 m up) ...
    assert heights["land"] < heights["hover"] - 3.0  # ... or descends out of the way


def test_a_drone_landing_at_its_goal_no_longer_counts_for_the_separation_reward(tmp_path: Path) -> None:
    data = yaml.safe_load(_world(tmp_path, after_goal="land").read_text())
    data["task"]["reward"]["separation"] = {"scale": -10, "distance_m": 30.0}  # any distance pays
    path = tmp_path / "tw_sep.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    env = make_parallel_env(str(path), seed=0)
    try:
        env.reset(seed=0)
        script = [CLIMB] * 4 + [FORWARD] * 8  # drone1 flies to its goal; drone0 hovers at its spawn
        paid, landed = [], False
        for step in range(len(script) + 3):
            actions = {a: (script[step] if a == "drone1" and step < len(script) else HOVER) for a in env.agents}
            _, _, _, _, infos = env.step(actions)
            paid.append((landed, infos["drone0"]["reward_terms"]["separation"]))
            landed = landed or infos.get("drone1", {}).get("outcome") == "goal"
        assert any(not gone and value < 0 for gone, value in paid)  # drone1 in the air: drone0 pays
        after = [value for gone, value in paid if gone]
        assert after and all(value == 0 for value in after)  # drone1 landing: out of the airspace
    finally:
        env.close()


def test_a_drone_hovering_at_its_goal_keeps_its_separation_and_a_landing_one_does_not(tmp_path: Path) -> None:
    # drone1 flies to its goal in drone0's yard (4.8 m from drone0's spawn), then drone0 climbs
    # toward it: 2.7 m away at 3 m up, inside min_separation_m while drone1 hovers there
    script = [CLIMB] * 4 + [FORWARD] * 8
    ends = {}
    for after in ("hover", "land"):
        env = make_parallel_env(str(_world(tmp_path, after_goal=after, min_separation_m=3.0)), seed=0)
        try:
            env.reset(seed=0)
            outcome1, infos0 = None, []
            for step in range(len(script) + 4):
                if "drone0" not in env.agents:
                    break
                mine = script[step] if step < len(script) else HOVER
                theirs = HOVER if outcome1 is None else CLIMB
                actions = {a: (mine if a == "drone1" else theirs) for a in env.agents}
                _, _, _, _, infos = env.step(actions)
                outcome1 = infos.get("drone1", {}).get("outcome") or outcome1
                infos0.append(infos["drone0"])
            assert outcome1 == "goal"
            ends[after] = infos0[-1]
        finally:
            env.close()
    assert ends["hover"]["outcome"] == "crash" and ends["hover"]["reward_terms"]["crash"] == -100
    assert ends["land"]["outcome"] is None  # drone1 left the airspace: drone0 flies on


@pytest.mark.parametrize(("key", "value", "message"), [
    ("after_goal", "teleport", r"task.end.after_goal: expected one of hover, land"),
    ("conflict_blame", "id", r"task.end.conflict_blame: expected one of both, give_way"),
    ("conflict_m", -1, r"task.end.conflict_m"),
    ("min_separation_m", -0.5, r"task.end.min_separation_m"),
])
def test_bad_end_settings_are_one_line_errors(tmp_path: Path, key: str, value: object, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        make_parallel_env(str(_world(tmp_path, **{key: value})), seed=0)


def test_lidar_tells_a_crash_caused_only_by_another_drone(tmp_path: Path) -> None:
    env = make_parallel_env(str(_world(tmp_path, conflict_blame="both")), seed=0)
    try:
        env.reset(seed=0)
        for step in range(9):
            env.step({a: _head_on_in_the_window(step) for a in env.agents})
            scans = env.runner.snapshot.scans
            if any(s.crash for s in scans):
                break
        assert any(s.crash for s in scans)
        assert all(s.crash_by_vehicles for s in scans if s.crash)
        assert np.isfinite([s.min_m for s in scans]).all()
    finally:
        env.close()
