"""Priority without identity bias: who yields follows the scenario's priority rule, not
the drone id. A rule set that yields on `own_priority` (step aside, hover until the other has
passed) flies the head-on scenario twice, the
second time with the drones' spawn points (and goals) swapped: the yielding drone changes with
the spawn points, because the priority input comes from where a drone starts
(`lower_coordinate_yields`), never from its index."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from sitl_bridge.envs import make_parallel_env, worlds_dir
from sitl_bridge.rl.analysis.behaviour import classify_episode
from sitl_bridge.rl.analysis.rule_policy import rule_policy
from sitl_bridge.rl.common.drones_env import DronesEnv
from sitl_bridge.rl.evaluation.rollout import rollout

WORLD = worlds_dir() / "two_drones_empty_relative.yaml"
YIELD_RULES = {
    "name": "no right of way: step aside and hover while the other passes",
    "covers": [WORLD.name],
    "frame": "goal",
    "rules": [
        {"text": "no right of way, the other drone ahead within 6 m, not yet aside: step right",
         "when": [{"feature": "own_priority", "op": "<", "value": 0.5},
                  {"feature": "travel_others[1]", "op": ">", "value": 0.0},
                  {"feature": "travel_others[1]", "op": "<", "value": 6.0},
                  {"feature": "travel_goal_offset[0]", "op": ">", "value": -1.5}],
         "action": "right"},
        {"text": "no right of way, the other drone ahead within 6 m or not yet 2 m past: hover",
         "when": [{"feature": "own_priority", "op": "<", "value": 0.5},
                  {"feature": "travel_others[1]", "op": ">", "value": -2.0},
                  {"feature": "travel_others[1]", "op": "<", "value": 6.0}],
         "action": "hover"},
        {"text": "otherwise fly toward the goal", "action": "toward goal"},
    ],
}


def _swapped(tmp_path: Path, world: Path = WORLD) -> Path:
    """The same scenario with the two vehicles' spawns (and so their goals) exchanged."""
    data = yaml.safe_load(world.read_text())
    first, second = data["world"]["vehicles"]
    first["spawn"], second["spawn"] = second["spawn"], first["spawn"]
    first["goal"], second["goal"] = second["goal"], first["goal"]
    path = tmp_path / f"{world.stem}_swapped.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _yielders(world: Path, rules: Path) -> list[int]:
    env = DronesEnv(make_parallel_env(str(world), autopilot="direct"))
    try:
        traces = rollout(env, rule_policy(rules, world), [0])
    finally:
        env.env.close()
    episode = classify_episode(traces)
    assert episode.success, [(d.drone, d.outcome) for d in episode.drones]
    assert episode.follows_priority is True
    return [d.drone for d in episode.yielders]


def test_who_yields_follows_the_priority_rule_not_the_drone_id(tmp_path: Path) -> None:
    rules = tmp_path / "yield.yaml"
    rules.write_text(yaml.safe_dump(YIELD_RULES, sort_keys=False))
    # drone 0 starts further south: lower priority, it yields
    assert _yielders(WORLD, rules) == [0]
    # spawn points swapped: drone 1 now starts further south and is the one that yields
    assert _yielders(_swapped(tmp_path), rules) == [1]


TW = worlds_dir() / "two_drones_window_relative.yaml"
TW_RUN = Path(__file__).resolve().parents[1] / "docs" / "results" / "runs" / "scenarios" / TW.stem / "seed1"


@pytest.mark.slow
def test_a_trained_tw_policy_goes_through_the_window_by_priority_not_by_id(tmp_path: Path) -> None:
    """The committed TW seed-1 policy flown as shipped and with the spawns swapped: the drone that
    goes through the window first is the one with right of way, so it changes with the spawn
    point (session 10: 17 of 17 and 20 of 20 successful episodes in priority order)."""
    from sitl_bridge.envs.scenario import load_scenario
    from sitl_bridge.rl.analysis.behaviour import classify, openings
    from sitl_bridge.rl.evaluation.rollout import eval_seeds
    from sitl_bridge.rl.learner.policy import policy_from_checkpoint

    (checkpoint,) = TW_RUN.glob("*/best.safetensors")
    firsts = []
    for world in (TW, _swapped(tmp_path, TW)):
        scenario = load_scenario(world)
        env = DronesEnv(make_parallel_env(str(world), autopilot="direct"))
        try:
            traces = rollout(env, policy_from_checkpoint(checkpoint), eval_seeds(1_000_000, 10))
        finally:
            env.env.close()
        episodes = [e for e in classify(traces, priority_rule=scenario.task.priority,
                                        shared_openings=openings(scenario.world.obstacles)) if e.success]
        assert len(episodes) >= 7
        assert sum(bool(e.order_follows_priority) for e in episodes) >= 0.9 * len(episodes)
        firsts.append({min(e.drones, key=lambda d: d.opening_step).drone for e in episodes})
    assert firsts == [{1}, {0}]  # drone 1 starts north (right of way); swapped, drone 0 does
