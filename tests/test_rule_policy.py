"""Rule sets flown as scripted policies (`eval --rules`, `verify_rules`) on the real scenario envs
(`direct` backend, a few episodes), their condition logic, and their one-line config errors."""

from __future__ import annotations

import argparse
import json
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest
import yaml

from sitl_bridge.commands import eval as eval_command
from sitl_bridge.envs.features import observation_layout
from sitl_bridge.envs.scenario import load_scenario
from sitl_bridge.errors import ConfigError
from sitl_bridge.rl.analysis.rule_policy import (
    HOVER,
    Condition,
    bind,
    load_rules,
    parse_feature,
    rule_policy,
    verify_rules,
)
from sitl_bridge.rl.analysis.tree_policy import Leaf, Split, TreePolicy, feature_labels, tree_rules
from sitl_bridge.rl.common.action_names import action_code, action_name
from sitl_bridge.rl.evaluation.evaluate import EvalResult

REPO = Path(__file__).resolve().parent.parent
WORLDS = REPO / "worlds"
EMPTY = str(WORLDS / "empty.yaml")            # position 0:3, orientation 3:6, lidar 6:41, dummy 41:51
OBSTACLE = str(WORLDS / "obstacle.yaml")
TOWARD_GOAL = str(WORLDS / "rules" / "toward_goal.yaml")
CLIMB_OVER = str(WORLDS / "rules" / "climb_over.yaml")


def cli(*argv: str) -> int:
    parser = argparse.ArgumentParser()
    eval_command.register(parser.add_subparsers())
    args = parser.parse_args(list(argv))
    return args.func(args)


def write_rules(tmp_path: Path, body: str, name: str = "rules.yaml") -> str:
    path = tmp_path / name
    path.write_text(body)
    return str(path)


def eval_rules_json(capsys: pytest.CaptureFixture[str], *argv: str) -> dict:
    assert cli("eval", *argv, "--json") == 0
    return json.loads(capsys.readouterr().out)


# -- flown in scenarios built for them -----------------------------------------------------------

def test_toward_goal_reaches_the_goal_with_the_checkpoint_eval_keys(capsys: pytest.CaptureFixture[str]) -> None:
    result = eval_rules_json(capsys, "--rules", TOWARD_GOAL, "--world", EMPTY, "--episodes", "2")
    assert set(result) == {f.name for f in fields(EvalResult)} | {"episode_seed", "separation"}
    assert result["episodes"] == 2 and result["success_rate"] == 1.0 and result["crash_rate"] == 0.0


def test_always_down_crashes_and_hover_times_out(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    down = write_rules(tmp_path, "frame: world\nrules:\n  - action: down\n", "down.yaml")
    result = eval_rules_json(capsys, "--rules", down, "--world", EMPTY, "--episodes", "1")
    assert result["crash_rate"] == 1.0 and result["mean_steps"] < 5  # 2.5 m up at 1 m/s

    short = tmp_path / "short_empty.yaml"  # empty.yaml with 4-step episodes: hovering runs out of time
    short.write_text((WORLDS / "empty.yaml").read_text().replace("max_steps: 20", "max_steps: 4"))
    hover = write_rules(tmp_path, "frame: world\nrules:\n  - action: 7\n", "hover.yaml")
    result = eval_rules_json(capsys, "--rules", hover, "--world", str(short), "--episodes", "1")
    assert result["timeout_rate"] == 1.0 and result["mean_steps"] == 4


def test_no_rule_holding_means_hover(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    short = tmp_path / "short_empty.yaml"
    short.write_text((WORLDS / "empty.yaml").read_text().replace("max_steps: 20", "max_steps: 3"))
    never = write_rules(tmp_path, "frame: world\nrules:\n  - when: [{feature: 'position[2]', op: '>', value: 100}]\n"
                                  "    action: toward goal\n")
    result = eval_rules_json(capsys, "--rules", never, "--world", str(short), "--episodes", "1")
    assert result["timeout_rate"] == 1.0


def test_the_lidar_conditions_decide_the_obstacle_scenario(capsys: pytest.CaptureFixture[str]) -> None:
    # --world defaults to the first covered scenario (obstacle.yaml)
    climb = eval_rules_json(capsys, "--rules", CLIMB_OVER, "--episodes", "1")
    assert climb["world"].endswith("obstacle.yaml") and climb["success_rate"] == 1.0
    straight = eval_rules_json(capsys, "--rules", TOWARD_GOAL, "--world", OBSTACLE, "--episodes", "1")
    assert straight["crash_rate"] == 1.0


def test_verify_rules_flies_covered_and_simpler_scenarios() -> None:
    report = verify_rules(CLIMB_OVER, [EMPTY], episodes=1, seed=0)
    assert list(report) == ["obstacle", "empty"]
    assert report["obstacle"]["covered"] and report["obstacle"]["success"] == 1.0
    assert report["obstacle"]["collision_rate"] == 0.0 and report["obstacle"]["episodes"] == 1
    assert sum(report["obstacle"]["rules_fired"].values()) == pytest.approx(1.0)
    # empty.yaml has 35 lidar rays: the rule set cannot be flown there, and says why
    assert not report["empty"]["covered"] and "lidar[46]" in report["empty"]["skipped"]

    report = verify_rules(TOWARD_GOAL, [OBSTACLE], episodes=1, seed=0)
    assert report["empty"]["success"] == report["random_goal"]["success"] == 1.0
    assert report["obstacle"]["collision_rate"] == 1.0 and not report["obstacle"]["covered"]


def test_a_traffic_rule_is_left_out_where_there_is_no_other_drone(tmp_path: Path) -> None:
    # the thesis's loop flies a traffic rule set in the one-drone scenarios before it: its rules
    # about the other drone do not apply there (the feature is not observed), the rest fly
    path = write_rules(tmp_path, f"""
frame: goal
covers: [{WORLDS / "two_drones_empty_relative.yaml"}]
rules:
  - text: no right of way, yield
    when: [{{feature: own_priority, op: "<", value: 0.5}}]
    action: hover
  - {{text: otherwise fly toward the goal, action: toward goal}}
""")
    with pytest.raises(ConfigError, match="own_priority"):
        rule_policy(path, EMPTY)
    policy = rule_policy(path, EMPTY, leave_out_absent=True)
    assert policy.left_out == (0,) and policy(np.zeros(51)) == 6
    report = verify_rules(path, [EMPTY], episodes=1, seed=0)
    assert report["empty"]["rules_left_out"] == ["no right of way, yield"]
    assert report["empty"]["success"] == 1.0
    assert report["two_drones_empty_relative"]["rules_left_out"] == []


# -- the logic: layout, features, ops, first match -------------------------------------------------

def test_observation_layout_follows_the_feature_list() -> None:
    layout = observation_layout(load_scenario(EMPTY).task.observation)
    assert layout == {"position": slice(0, 3), "orientation": slice(3, 6), "lidar": slice(6, 41),
                      "dummy": slice(41, 51)}
    assert observation_layout(load_scenario(OBSTACLE).task.observation)["lidar"] == slice(6, 53)


def test_parse_feature() -> None:
    assert parse_feature("lidar[17]") == ("lidar", 17)
    assert parse_feature(" travel_others [ 1 ] ") == ("travel_others", 1)
    assert parse_feature("own_priority") == ("own_priority", None)
    assert parse_feature("dummy@2[0]") == ("dummy@2", 0)  # a feature listed twice (observation_layout)
    for bad in ("lidar[-1]", "lidar[1", "lidar[x]", "3lidar", ""):
        assert parse_feature(bad) is None


@pytest.mark.parametrize(("op", "results"), [("<", (True, False, False)), ("<=", (True, True, False)),
                                             (">", (False, False, True)), (">=", (False, True, True)),
                                             ("==", (False, True, False)), ("!=", (True, False, True))])
def test_condition_ops(op: str, results: tuple[bool, bool, bool]) -> None:
    condition = Condition("lidar[0]", "lidar", 0, op, 2.0, "rules[0].when[0]")
    assert tuple(condition.holds(x) for x in (1.0, 2.0, 3.0)) == results


def test_first_rule_whose_conditions_all_hold_wins(tmp_path: Path) -> None:
    path = write_rules(tmp_path, """
frame: world
rules:
  - text: low and close ahead
    when:
      - {feature: "position[2]", op: "<", value: 1.0}
      - {feature: "lidar[17]", op: "<=", value: 2.0}
    action: up
  - text: low
    when: [{feature: "position[2]", op: "<", value: 1.0}]
    action: north
  - {text: otherwise, action: 6}
""")
    policy = rule_policy(path, EMPTY)
    obs = np.zeros(51)
    obs[6 + 17] = 1.5
    assert policy(obs) == action_code("up")              # both conditions hold
    obs[6 + 17] = 2.5
    assert policy(obs) == action_code("north")           # only the second rule's
    obs[2] = 3.0
    assert policy(obs) == 6                              # the unconditional rule
    assert policy.fired == [1, 1, 1, 0]
    with pytest.raises(ValueError, match="51 observation values, got 50"):
        policy(np.zeros(50))


def test_a_distilled_tree_flies_as_it_decides(tmp_path: Path) -> None:
    # h-distill's rules document (`tree_rules`) read back by this loader decides as the tree does.
    up, hover = action_code("up"), action_code("hover")
    tree = TreePolicy(Split(1, 2.5, Leaf(action_code("north"), 4),
                            Split(2, 3.0, Split(6 + 17, 1.5, Leaf(up, 2), Leaf(hover, 1)), Leaf(6, 3))))
    labels = feature_labels(observation_layout(load_scenario(EMPTY).task.observation), 51)
    document = tree_rules(tree, labels, frame="world", name="tree", covers=["empty.yaml"], source="test")
    path = write_rules(tmp_path, yaml.safe_dump(document, sort_keys=False))
    policy = rule_policy(path, EMPTY)
    rng = np.random.default_rng(0)
    for _ in range(300):
        obs = rng.uniform(0.0, 6.0, size=51).astype(np.float32)
        assert policy(obs) == tree(obs)
    assert policy.fired[-1] == 0  # the leaves cover every observation: never the hover fallback


def test_names_in_the_rules_frame(tmp_path: Path) -> None:
    path = write_rules(tmp_path, "frame: goal\nrules:\n  - action: forward\n  - action: toward goal\n")
    rules = load_rules(path)
    assert [r.action for r in rules.rules] == [3, 6]
    assert action_name(3, "goal") == "forward" and action_name(3, "world") == "north"
    assert "if always: forward" in rules.describe()


def test_frame_independent_rules_fly_in_either_frame(tmp_path: Path) -> None:
    path = write_rules(tmp_path, "frame: goal\nrules:\n  - {action: up, when: [{feature: 'lidar[0]', op: '<', "
                                 "value: 1}]}\n  - action: toward goal\n")
    assert bind(load_rules(path), load_scenario(EMPTY))(np.full(51, 5.0)) == 6
    assert action_code("hover") == HOVER


# -- one-line errors naming the key path ----------------------------------------------------------

@pytest.mark.parametrize(("body", "message"), [
    ("frame: world\nrules: [\n", r"invalid YAML at line"),
    ("frame: sideways\nrules:\n  - action: up\n", r": frame: expected one of world, goal, got 'sideways'"),
    ("rules:\n  - action: up\n", r": frame: required key is missing"),
    ("frame: world\nrules: []\n", r": rules: expected a list of at least 1 items"),
    ("frame: world\nrules:\n  - action: up\n  - action: forward\n",
     r": rules\[1\]\.action: expected an action of the world frame \(east, .*\) or a code 0..7, got 'forward'"),
    ("frame: world\nrules:\n  - action: 8\n", r": rules\[0\]\.action: expected an integer >= 0 <= 7, got 8"),
    ("frame: world\nrules:\n  - {action: up, when: [{feature: 'lidr[3]', op: '<', value: 1}]}\n",
     r": rules\[0\]\.when\[0\]\.feature: expected NAME\[INDEX\] or NAME with NAME an observation feature"),
    ("frame: world\nrules:\n  - {action: up, when: [{feature: 'lidar[3]', op: '=<', value: 1}]}\n",
     r": rules\[0\]\.when\[0\]\.op: expected one of <, <=, >, >=, ==, !=, got '=<'"),
    ("frame: world\nrules:\n  - {action: up, when: [{feature: 'lidar[3]', op: '<', value: near}]}\n",
     r": rules\[0\]\.when\[0\]\.value: expected a number, got 'near'"),
    ("frame: world\nrules:\n  - {action: up, wen: []}\n", r": rules\[0\]\.wen: unknown key"),
])
def test_malformed_rule_files(tmp_path: Path, body: str, message: str) -> None:
    path = write_rules(tmp_path, body)
    with pytest.raises(ConfigError, match=message) as caught:
        load_rules(path)
    assert str(caught.value).startswith(path) and "\n" not in str(caught.value)


@pytest.mark.parametrize(("feature", "message"), [
    ("goal_offset[0]", r"expected a feature of the observation of .*empty\.yaml \(position\[0\.\.2\], "
                       r"orientation\[0\.\.2\], lidar\[0\.\.34\], dummy\[0\.\.9\]\), got 'goal_offset\[0\]'"),
    ("lidar[35]", r"expected an index 0\.\.34 of lidar in .*empty\.yaml, got 'lidar\[35\]'"),
    ("lidar", r"expected lidar\[INDEX\] \(lidar has 35 values in .*empty\.yaml\), got 'lidar'"),
])
def test_features_are_checked_against_the_scenario(tmp_path: Path, feature: str, message: str) -> None:
    path = write_rules(tmp_path, f"frame: world\nrules:\n  - action: up\n  - {{action: 6, when: "
                                 f"[{{feature: 'position[0]', op: '>', value: 0}}, {{feature: '{feature}', "
                                 f"op: '<', value: 1}}]}}\n")
    with pytest.raises(ConfigError, match=r": rules\[1\]\.when\[1\]\.feature: " + message) as caught:
        rule_policy(path, EMPTY)
    assert "\n" not in str(caught.value)


def test_frame_mismatch_for_a_frame_dependent_action(tmp_path: Path) -> None:
    path = write_rules(tmp_path, "frame: goal\nrules:\n  - action: toward goal\n  - action: right\n")
    with pytest.raises(ConfigError, match=r"rules\.yaml: frame: expected world \(the action frame of .*empty\.yaml; "
                                          r"rules\[1\]\.action 'right' depends on it\), got 'goal'"):
        rule_policy(path, EMPTY)


def test_cli_wants_exactly_one_of_checkpoint_and_rules(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli("eval", "--world", EMPTY) == 2
    assert cli("eval", str(tmp_path), "--rules", TOWARD_GOAL) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 2 and "exactly one" in err
    bad = write_rules(tmp_path, "frame: world\nrules:\n  - {action: up, when: [{feature: 'lidar[99]', op: '<', "
                                "value: 1}]}\n")
    assert cli("eval", "--rules", bad, "--world", EMPTY) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {bad}: rules[0].when[0].feature: expected an index 0..34") and err.count("\n") == 1
    nothing = write_rules(tmp_path, "frame: world\nrules:\n  - action: up\n", "uncovered.yaml")
    assert cli("eval", "--rules", nothing) == 2
    assert "covers: expected a scenario to fly in (or give --world), got []" in capsys.readouterr().err
