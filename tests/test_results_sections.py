"""The report's behaviour, rules, trees and backends sections and its grids of typical episodes, on a tiny
two-seed experiment (empty and random_goal, two training episodes per run): the sections hold the
issue's keys with the right types, the rules YAMLs exist and fly, random_goal's rules are verified
in empty (the thesis's order), the grids are drawn, scenarios without runs say "not run", and a
second report reuses the cached flights."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from sitl_bridge.cli import main as cli
from sitl_bridge.data_paths import worlds_dir
from sitl_bridge.errors import ConfigError
from sitl_bridge.rl.experiments.runner import load_experiment

pytest.importorskip("scipy")
pytest.importorskip("sklearn")
EMPTY = worlds_dir() / "empty.yaml"
RANDOM_GOAL = worlds_dir() / "random_goal.yaml"
TINY_TRAIN = "{episodes: 2, eval_every: 0, eval_episodes: 1, batch_size: 8, layers: 2, hidden_units: 8}"
C0 = np.array([0x1F, 0x77, 0xB4]) / 255  # matplotlib's first colour: drone 0's path


def _experiment(folder: Path, report: str = "") -> Path:
    path = folder / "sections.yaml"
    path.write_text(f"""experiment:
  name: sections
  seeds: 0-1
  eval_episodes: 2
  scenarios:
    - world: {EMPTY}
      train: {TINY_TRAIN}
    - world: {RANDOM_GOAL}
      train: {TINY_TRAIN}
  report: {report or "{behaviour_episodes: 2, verify_episodes: 2, distill_episodes: 2, distill_iterations: 1, "
                     "picture_episodes: 2, picture_cells: 4, backend_episodes: 2, backend_seeds: 1}"}
""")
    return path


@pytest.fixture(scope="module")
def experiment(tmp_path_factory) -> tuple[Path, dict]:
    folder = tmp_path_factory.mktemp("sections")
    out = folder / "out"
    assert cli(["experiment", str(_experiment(folder)), "--out", str(out), "--workers", "1"]) == 0
    return out, json.loads((out / "results.json").read_text())


def _settings(out: Path):  # noqa: ANN202 - ReportSettings
    return load_experiment(out.parent / "sections.yaml").report


def test_behaviour_section(experiment) -> None:
    _, results = experiment
    assert set(results["behaviour"]) == {"empty", "random_goal"}
    for stem, b in results["behaviour"].items():
        assert b["status"] == "done"
        assert b["seed_labels"] == ["0", "1"] and b["episodes_per_seed"] == 2
        assert [r["label"] for r in b["per_seed"]] == ["0", "1"]
        for seed in b["per_seed"]:  # every drone-episode of the seed classified once
            assert sum(seed["counts"].values()) == 2 and sum(seed["outcomes"].values()) == 2
        assert isinstance(b["split"], dict) and all(0.0 <= v <= 1.0 for v in b["split"].values())
        assert isinstance(b["split_text"], str) and b["frame"] == "world"
        assert [c["rule"] for c in b["thesis_rules"]] == [0, 1, 2, 3, 4, 5]
        for check in b["thesis_rules"]:
            assert check["recovered"] in (True, False, None) and isinstance(check["support_seeds"], int)
        assert b["rules_file"] == f"rules/{stem}.yaml"


def test_rules_section_is_verified_in_the_simpler_scenarios(experiment) -> None:
    out, results = experiment
    rules = results["rules"]
    assert isinstance(rules, list)
    for rule in rules:
        assert rule["scenario"] in ("empty", "random_goal")
        assert isinstance(rule["text"], str) and rule["text"]
        assert isinstance(rule["support_seeds"], int) and isinstance(rule["support_episodes"], int)
        assert 0 <= rule["support_seeds"] <= 2 and 0 <= rule["support_episodes"] <= rule["episodes"]
        assert isinstance(rule["verification"], dict)
        if rule["in_yaml"]:
            assert rule["verification"] == results["behaviour"][rule["scenario"]]["verification"]
    verification = results["behaviour"]["random_goal"]["verification"]
    assert list(verification) == ["random_goal", "empty"]  # its own scenario, then the simpler one (E < ER)
    assert verification["random_goal"]["covered"] and not verification["empty"]["covered"]
    assert list(results["behaviour"]["empty"]["verification"]) == ["empty"]
    for stem, check in verification.items():
        assert 0.0 <= check["success"] <= 1.0 and 0.0 <= check["collision_rate"] <= 1.0
        assert check["episodes"] == 2
        assert check["network_success"] == results[stem]["success_mean"]
    report = (out / "RESULTS.md").read_text()
    assert "## Rules" in report and "[rules/random_goal.yaml](rules/random_goal.yaml)" in report
    assert "### The thesis's rules 0-5" in report and "Not run (" not in report


def test_rules_yamls_exist_and_fly(experiment) -> None:
    from sitl_bridge.rl.analysis.rule_policy import load_rules, verify_rules

    out, _ = experiment
    for stem in ("empty", "random_goal"):
        for path in (out / "rules" / f"{stem}.yaml", out / "trees" / f"{stem}.yaml"):
            assert load_rules(path).covers == (f"{stem}.yaml",)
            flown = verify_rules(path, episodes=1)  # covers finds the scenario, not the rules file itself
            assert set(flown) == {stem} and flown[stem]["covered"] and flown[stem]["episodes"] == 1
    world = str(RANDOM_GOAL)
    assert cli(["eval", "--rules", str(out / "rules" / "random_goal.yaml"), "--world", world, "--episodes", "1"]) == 0


def test_trees_section(experiment) -> None:
    out, results = experiment
    assert set(results["trees"]) == {"empty", "random_goal"}
    for stem, tree in results["trees"].items():
        assert tree["status"] == "done"
        seeds = results[stem]["seeds"]
        assert tree["seed"] == max(seeds, key=lambda s: (s["greedy_success"], -s["seed"]))["seed"]
        assert isinstance(tree["depth"], int) and 0 <= tree["depth"] <= 6 and tree["leaves"] >= 1
        for key in ("fidelity", "success", "network_success"):
            assert isinstance(tree[key], float) and 0.0 <= tree[key] <= 1.0
        assert isinstance(tree["meets_target"], bool) and tree["episodes"] == 2
        assert tree["text"] and tree["text"] in (out / tree["text_file"]).read_text()
    assert "## Distilled decision trees" in (out / "RESULTS.md").read_text()


def test_grids_of_typical_episodes_are_drawn(experiment) -> None:
    from matplotlib.image import imread

    out, results = experiment
    report = (out / "RESULTS.md").read_text()
    for stem in ("empty", "random_goal"):
        grid = results[stem]["episodes_grid"]
        assert grid["figure"] == f"figures/{stem}_episodes.png" and f"]({grid['figure']})" in report
        assert grid["episodes"] == 4 and 1 <= len(grid["cells"]) <= 4
        assert sum({c["behaviour"]: c["count"] for c in grid["cells"]}.values()) <= 4
        image = imread(out / grid["figure"])[..., :3]
        path_pixels = np.all(np.abs(image - C0) < 0.03, axis=-1).sum()
        assert path_pixels > 50  # drone 0's paths are drawn, not just empty axes


def test_a_second_report_reuses_the_flights_and_says_not_run(experiment, tmp_path) -> None:
    """A scenario without finished runs is "not run" in every section; the others come from the
    cache (their rules and tree files are not written again)."""
    from sitl_bridge.rl.experiments import backends_section as backend_results
    from sitl_bridge.rl.experiments import report as experiment_report
    from sitl_bridge.rl.experiments import rules_section as rule_results
    from sitl_bridge.rl.experiments import trees_section as distill_results

    out, results = experiment
    files = [out / "rules" / "empty.yaml", out / "trees" / "empty.txt", out / "figures" / "empty_episodes.png"]
    before = [f.stat().st_mtime_ns for f in files]
    again = {k: v for k, v in results.items() if k not in ("behaviour", "rules", "trees", "backends")}
    again["window"] = {"world": str(worlds_dir() / "window.yaml"), "seeds": [], "unfinished": [0, 1],
                       "success_mean": None, "success_ci95": None}
    settings = _settings(out)
    experiment_report.write_figures(again, out, say=lambda _: None, settings=settings)
    rule_results.add_results_section(again, out, settings=settings, say=lambda _: None)
    distill_results.add_results_section(again, out, settings=settings, say=lambda _: None)
    said: list[str] = []
    backend_results.add_results_section(again, out, settings=settings, say=said.append)
    assert [f.stat().st_mtime_ns for f in files] == before
    assert not [line for line in said if line.startswith("  ")]  # no backend flown again
    assert again["backends"]["empty"] == results["backends"]["empty"]
    assert {b["skipped"] for b in again["backends"]["window"].values()} == {"no finished runs"}
    assert again["behaviour"]["window"]["status"] == "not run" and again["trees"]["window"]["status"] == "not run"
    assert again["behaviour"]["empty"] == results["behaviour"]["empty"]
    assert again["trees"]["random_goal"] == results["trees"]["random_goal"]
    assert list(again["behaviour"]["random_goal"]["verification"]) == ["random_goal", "empty"]  # order kept
    text = experiment_report.render(again, json.loads((out / "experiment.json").read_text()))
    assert "| `window` | not run (no finished runs) |" in text
    assert "- `window`: not run" in text and "### `window`" in text
    assert "| `window` | all | skipped: no finished runs |" in text


def test_backends_section(experiment) -> None:
    """Seed 0's policy flown on direct and the real stub, same episodes; px4 only with PX4_BIN."""
    out, results = experiment
    assert isinstance(results["transfer"], dict)  # the comparisons keep their key
    assert set(results["backends"]) == {"empty", "random_goal"}
    for backends in results["backends"].values():
        assert list(backends) == ["direct", "stub", "px4"]
        for name in ("direct", "stub"):
            b = backends[name]
            assert "skipped" not in b and [s["seed"] for s in b["seeds"]] == [0]  # backend_seeds: 1
            (seed,) = b["seeds"]
            assert seed["episodes"] == 2 and seed["drone_episodes"] == 2
            assert b["success_mean"] == seed["success"] and b["collision_mean"] == seed["collision"]
            lo, hi = b["success_ci95"]
            assert lo <= b["success_mean"] <= hi and sum(b["outcomes"].values()) == 2
            assert (seed["mean_steps_success"] is None) == (seed["success"] == 0)
        stub = backends["stub"]
        assert stub["same_actions"]["compared"] == 2 and isinstance(stub["differs"], bool)
        assert (stub["why"] is not None) == stub["differs"]
        px4 = backends["px4"]
        if os.path.isfile(os.environ.get("PX4_BIN", "")):
            assert "skipped" not in px4 and px4["seeds"][0]["episodes"] == 2
        else:
            assert "PX4_BIN" in px4["skipped"] and px4["seeds"] == [] and px4["success_mean"] is None
    report = (out / "RESULTS.md").read_text()
    assert "## Transfer between autopilot backends" in report and "pooled Wilson" in report
    assert "| `empty` | stub | 1 | 2 |" in report and "| `random_goal` | direct | 1 | 2 |" in report


def test_backend_flights_are_cached_per_seed(experiment) -> None:
    """A second report with every seed flies only the seed not flown before, on each backend."""
    import dataclasses

    from sitl_bridge.rl.experiments import backends_section as backend_results

    out, results = experiment
    said: list[str] = []
    settings = dataclasses.replace(_settings(out), backend_seeds=0)
    entries = backend_results.scenario_backends("empty", results, out, settings, said.append)
    names = ["direct", "stub"] + (["px4"] if os.path.isfile(os.environ.get("PX4_BIN", "")) else [])
    assert [line for line in said if line.startswith("  ")] == [
        f"  empty seed 1 on {name}: 2 greedy episodes" for name in names]
    for name in names:
        assert [s["seed"] for s in entries[name]["seeds"]] == [0, 1]
        assert entries[name]["seeds"][0] == results["backends"]["empty"][name]["seeds"][0]


def test_simpler_scenarios_follow_the_thesis_and_the_comparisons() -> None:
    from sitl_bridge.rl.experiments.rules_section import simpler_scenarios

    def scenario() -> dict:
        return {"world": "x", "seeds": []}

    results = {stem: scenario() for stem in ("empty", "random_goal", "two_drones_empty", "window", "mine")}
    results["transfer"] = {"w_mine": {"stages": ["window", "mine"]}}
    order = simpler_scenarios(results)
    assert order["two_drones_empty"] == ["empty", "random_goal"]  # TE after ER after E, transitively
    assert order["random_goal"] == ["empty"] and order["empty"] == []
    assert order["mine"] == ["window"] and order["window"] == []


def test_report_settings_in_the_experiment_file(tmp_path) -> None:
    settings = load_experiment(_experiment(tmp_path, "{verify_episodes: 7}")).report
    assert settings.verify_episodes == 7 and settings.behaviour_episodes == 10  # the rest: defaults
    with pytest.raises(ConfigError, match=r"report\.distill_depth: expected an integer >= 1 <= 12, got 0"):
        load_experiment(_experiment(tmp_path, "{distill_depth: 0}"))
    assert load_experiment(_experiment(tmp_path, "{backend_seeds: 0}")).report.backend_seeds == 0  # 0: all seeds
    with pytest.raises(ConfigError, match=r"report\.backend_episodes: expected an integer >= 1"):
        load_experiment(_experiment(tmp_path, "{backend_episodes: 0}"))
    with pytest.raises(ConfigError, match=r"report\.episodes: unknown key"):
        load_experiment(_experiment(tmp_path, "{episodes: 3}"))
