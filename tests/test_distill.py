"""Distilled policies: VIPER weights and DAgger aggregation on small arrays, the tree as text and as
a rules YAML, a scripted shallow-tree teacher recovered in the real `empty` scenario (`direct`
backend), and `sitl-bridge distill` end to end on a tiny trained run."""

from __future__ import annotations

import argparse
import importlib
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from sitl_bridge.envs.features import index_words, observation_layout
from sitl_bridge.envs.scenario import load_scenario
from sitl_bridge.errors import load_yaml
from sitl_bridge.rl.analysis.distill import (
    Candidate,
    Dataset,
    aggregate,
    best_candidate,
    distill_policy,
    fidelity,
    fit_tree,
    label,
    sample_weights,
    viper_weights,
)
from sitl_bridge.rl.analysis.tree_policy import (
    Leaf,
    Split,
    TreePolicy,
    feature_labels,
    merge_equal_leaves,
    tree_rules,
    tree_text,
)
from sitl_bridge.rl.common.action_names import action_code
from sitl_bridge.rl.common.drones_env import DronesEnv, scenario_env_factory

pytest.importorskip("sklearn")

REPO = Path(__file__).resolve().parent.parent
EMPTY = str(REPO / "worlds" / "empty.yaml")  # position (rounded), orientation, 35 lidar rays, dummy
NORTH, UP, TOWARD_GOAL = 3, 5, 6


def test_viper_weight_is_the_q_gap_and_labels_are_greedy() -> None:
    q = np.array([[1.0, 3.0, 2.0], [0.5, 0.5, 0.5], [-1.0, 5.0, -4.0]])
    assert viper_weights(q).tolist() == [2.0, 0.0, 9.0]
    data = label(lambda states: q[: len(states)], np.zeros((3, 2)))
    assert data.actions.tolist() == [1, 0, 1] and data.weights.tolist() == [2.0, 0.0, 9.0]
    with pytest.raises(ValueError):
        viper_weights(np.zeros(3))
    # A network indifferent everywhere still leaves something to fit.
    assert sample_weights(np.zeros(4)).tolist() == [1.0] * 4
    assert sample_weights(np.array([0.0, 2.0])).tolist() == [0.0, 2.0]


def test_aggregation_keeps_every_labelled_state_in_order() -> None:
    first = Dataset(np.array([[0.0], [1.0]]), np.array([1, 2]), np.array([0.5, 1.5]))
    second = Dataset(np.array([[2.0]]), np.array([3]), np.array([4.0]))
    assert aggregate(None, first) is first
    both = aggregate(first, second)
    assert len(both) == 3
    assert both.states[:, 0].tolist() == [0.0, 1.0, 2.0]
    assert both.actions.tolist() == [1, 2, 3] and both.weights.tolist() == [0.5, 1.5, 4.0]


def test_weights_decide_between_conflicting_labels() -> None:
    # The same state labelled 2 once (the gap is large there) and 5 twice (gaps small):
    # VIPER's weights make the tree pick 2; unweighted, the majority 5 would win.
    states = np.array([[0.0], [0.0], [0.0], [1.0], [1.0]], dtype=np.float32)
    weighted = Dataset(states, np.array([2, 5, 5, 3, 3]), np.array([10.0, 1.0, 1.0, 1.0, 1.0]))
    tree = fit_tree(weighted, max_depth=3)
    assert tree(np.array([0.0])) == 2 and tree(np.array([1.0])) == 3
    flat = Dataset(states, weighted.actions, np.ones(5))
    assert fit_tree(flat, max_depth=3)(np.array([0.0])) == 5
    assert fidelity(tree, weighted) == pytest.approx(3 / 5)


def test_best_candidate_prefers_success_then_fidelity() -> None:
    tree = TreePolicy(Leaf(0))
    a = Candidate(0, 10, 1, 2, 0.99, 0.5, 1.0, tree)
    b = Candidate(1, 20, 2, 3, 0.90, 0.8, 0.0, tree)
    c = Candidate(2, 30, 2, 3, 0.95, 0.8, 0.0, tree)
    assert best_candidate([a, b, c]) is c
    assert best_candidate([a, a]) is a  # equals: the earlier, smaller data


TREE = TreePolicy(Split(1, 2.5,
                        Split(1, 1.5, Leaf(NORTH, 3), Leaf(NORTH, 1)),  # same action: merged on build
                        Split(2, 3.0, Split(1, 6.5, Leaf(UP, 2), Leaf(7, 1)), Leaf(TOWARD_GOAL, 3))))


def test_tree_policy_paths_text_and_rules_round_trip(tmp_path: Path) -> None:
    tree = TreePolicy(merge_equal_leaves(TREE.root))
    assert tree.depth == 3 and tree.leaves == 4
    assert tree(np.array([0.0, 2.0, 2.5])) == NORTH
    assert tree(np.array([0.0, 4.0, 2.5])) == UP and tree(np.array([0.0, 7.0, 2.5])) == 7
    assert tree(np.array([0.0, 4.0, 3.5])) == TOWARD_GOAL
    # Conditions on one feature are reduced to the tightest bound per side.
    conditions, leaf = tree.paths()[2]
    assert leaf.action == 7
    assert [(c.feature, c.op, c.value) for c in conditions] == [(1, ">", 6.5), (2, "<=", 3.0)]

    layout = observation_layout(load_scenario(EMPTY).task.observation)
    labels = feature_labels(layout, 51)
    assert labels[:4] == ["position[0]", "position[1]", "position[2]", "orientation[0]"]
    text = tree_text(tree, labels, "goal")
    assert "if position[1] <= 2.5:" in text and "position[2] <= 3" in text
    assert "forward" in text and "toward goal" in text and "hover" in text  # goal-frame names
    assert "where position = x, y, z" in text and "rays:" not in text  # no lidar test, no ray line

    document = tree_rules(tree, labels, frame="world", name="t", covers=["empty.yaml"], source="test")
    file = tmp_path / "rules.yaml"
    file.write_text(yaml.safe_dump(document, sort_keys=False, default_flow_style=None))
    loaded = load_yaml(file).value
    assert loaded == document and loaded["frame"] == "world" and loaded["covers"] == ["empty.yaml"]
    assert [r["action"] for r in loaded["rules"]] == ["north", "up", "hover", "toward goal"]
    # Flown as rules (first rule whose conditions all hold), the file decides as the tree does.
    index = {name: i for i, name in enumerate(labels)}
    ops = {"<=": np.less_equal, ">": np.greater}
    rng = np.random.default_rng(0)
    for obs in rng.uniform([-5, -3, 0], [5, 12, 6], size=(200, 3)):
        for rule in loaded["rules"]:
            if all(ops[c["op"]](obs[index[c["feature"]]], c["value"]) for c in rule.get("when", [])):
                assert action_code(rule["action"], "world") == tree(obs)
                break
        else:
            pytest.fail(f"no rule holds for {obs}")


def test_tree_text_says_where_each_ray_it_tests_points() -> None:
    scenario = load_scenario(EMPTY)  # 35 horizontal rays, the last one looking back
    layout = observation_layout(scenario.task.observation)
    labels = feature_labels(layout, 51)
    ahead, last = layout["lidar"].start + 17, layout["lidar"].stop - 1
    tree = TreePolicy(Split(ahead, 3.0, Leaf(UP, 2), Split(last, 1.0, Leaf(UP, 1), Leaf(TOWARD_GOAL, 3))))
    text = tree_text(tree, labels, "world", index_words(scenario.task.observation))
    assert text.splitlines()[-1] == "rays: lidar[17] ahead; lidar[34] behind"
    assert set(index_words(scenario.task.observation)) == set(range(layout["lidar"].start, last + 1))  # the rays only


def test_a_single_leaf_reads_as_always() -> None:
    tree = TreePolicy(Leaf(TOWARD_GOAL, 5))
    assert tree.depth == 0 and tree.leaves == 1
    assert tree_text(tree, ["x"], "world").startswith("always toward goal")
    assert tree_rules(tree, ["x"], frame="world", name="n", covers=[])["rules"] == [
        {"text": "always: toward goal (100% of states)", "action": "toward goal"}]


def scripted_q(states: np.ndarray) -> np.ndarray:
    """A teacher that is itself a depth-2 tree over the rounded position: north until y > 2.5, then
    up while z <= 2.5, then toward the goal; the Q gap varies so VIPER weights are not uniform."""
    states = np.asarray(states, dtype=np.float64)
    x, y, z = states[:, 0], states[:, 1], states[:, 2]
    action = np.where(y <= 2.5, NORTH, np.where(z <= 2.5, UP, TOWARD_GOAL))
    q = np.zeros((len(states), 8))
    q[np.arange(len(states)), action] = 1.0 + np.abs(x) + y
    return q


def test_a_shallow_tree_teacher_is_recovered_in_the_real_scenario() -> None:
    scenario = load_scenario(EMPTY)
    env = DronesEnv(scenario_env_factory(EMPTY)(0))

    def teacher(obs: np.ndarray) -> int:
        return int(np.argmax(scripted_q(np.asarray(obs)[None])[0]))

    try:
        result = distill_policy(env, scripted_q, teacher, layout=observation_layout(scenario.task.observation), frame="world",
                                world=EMPTY, covers=["empty.yaml"], max_depth=4, iterations=2, episodes=3)
    finally:
        env.close()
    assert result.fidelity >= 0.95 and result.fidelity_network_states >= 0.95
    assert result.depth <= 4 and len(result.candidates) == 2
    if result.fidelity == 1.0 and result.fidelity_network_states == 1.0:  # same decisions: same flights
        assert result.success == result.network_success and result.mean_return == result.network_return
    assert "position[1]" in result.text and "north" in result.text
    assert load_yaml_text(result.rules_yaml())["covers"] == ["empty.yaml"]
    json.dumps(result.to_dict())  # JSON-ready for the experiment runner


def load_yaml_text(text: str) -> dict:
    import tempfile

    with tempfile.NamedTemporaryFile("w", suffix=".yaml", delete=False) as handle:
        handle.write(text)
    try:
        return load_yaml(handle.name).value
    finally:
        Path(handle.name).unlink()


def cli(*argv: str) -> int:
    parser = argparse.ArgumentParser()
    subparsers = parser.add_subparsers()
    for name in ("train", "eval", "distill"):
        importlib.import_module(f"sitl_bridge.commands.{name}").register(subparsers)
    args = parser.parse_args(list(argv))
    return args.func(args)


def test_distill_command_on_a_tiny_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "runs"
    assert cli("train", EMPTY, "--episodes", "2", "--seed", "3", "--out", str(out), "--batch-size", "16",
               "--layers", "2", "--hidden-units", "16", "--eval-every", "0", "--eval-episodes", "0",
               "--no-progress") == 0
    (run,) = [p for p in out.iterdir() if p.is_dir()]
    capsys.readouterr()
    rules = tmp_path / "tree.yaml"
    assert cli("distill", str(run), "--max-depth", "3", "--iterations", "2", "--episodes", "2", "--json",
               "--rules-out", str(rules)) == 0
    result = json.loads(capsys.readouterr().out)
    assert 0 <= result["depth"] <= 3 and result["leaves"] >= 1
    assert 0.0 <= result["fidelity"] <= 1.0 and len(result["candidates"]) == 2
    document = load_yaml(rules).value
    assert document["covers"] == ["empty.yaml"] and document["frame"] == "world"
    assert len(document["rules"]) == result["leaves"]
    # The network's figures are those of `eval` on the same seed and episodes.
    assert cli("eval", str(run), "--episodes", "2", "--seed", "0", "--json") == 0
    evaluated = json.loads(capsys.readouterr().out)
    assert result["network_success"] == evaluated["success_rate"]
    assert result["network_return"] == pytest.approx(evaluated["mean_reward"])
    # A bad run directory is one line, exit 2.
    assert cli("distill", str(tmp_path), "--episodes", "1") == 2
    assert "error:" in capsys.readouterr().err
