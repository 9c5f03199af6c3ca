"""`sitl-bridge experiment`: the statistics on known numbers, the experiment file's checks, a
tiny two-seed experiment with a with/without-transfer comparison end to end (runs, report,
results.json), and its resume after an interruption (only the half-finished run is trained)."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import pytest
import yaml

from sitl_bridge.cli import main as cli
from sitl_bridge.data_paths import worlds_dir
from sitl_bridge.errors import ConfigError
from sitl_bridge.rl.common.stats import mann_whitney, mean_ci95, wilson_interval
from sitl_bridge.rl.experiments.results import compare, learning_time, summarize_seeds
from sitl_bridge.rl.experiments.runner import load_experiment, selected

pytest.importorskip("scipy")
REPO = Path(__file__).resolve().parents[1]
EMPTY = worlds_dir() / "empty.yaml"
SEED_KEYS = {"seed", "greedy_success", "collision_rate", "episodes_to_90", "wall_s"}


# -- statistics --------------------------------------------------------------------------------
def test_mean_ci95_is_the_student_t_interval() -> None:
    # mean 0.9, sd 0.1, n 3: half width t(0.975, 2) * 0.1 / sqrt(3), t(0.975, 2) = 4.302653 (tables)
    mean, (low, high) = mean_ci95([0.8, 0.9, 1.0])
    half = 4.302653 * 0.1 / math.sqrt(3)
    assert mean == pytest.approx(0.9)
    assert (low, high) == (pytest.approx(0.9 - half, abs=1e-6), pytest.approx(0.9 + half, abs=1e-6))
    assert mean_ci95([0.7]) == (0.7, None)
    assert mean_ci95([0.5, 0.5, 0.5]) == (0.5, (0.5, 0.5))


def test_wilson_interval_known_value() -> None:
    low, high = wilson_interval(5, 10)  # textbook: 5 of 10 -> [0.2366, 0.7634]
    assert (round(low, 4), round(high, 4)) == (0.2366, 0.7634)


def test_mann_whitney_without_ties_is_exact() -> None:
    test = mann_whitney([1, 2, 3], [4, 5, 6])
    # every a below every b: U = 0; exact two-sided p = 2 / C(6, 3) = 0.1; rank-biserial -1
    assert (test.u, test.p_value, test.effect_size) == (0.0, pytest.approx(0.1), -1.0)
    assert mann_whitney([4, 5, 6], [1, 2, 3]).effect_size == 1.0


def test_mann_whitney_with_ties_by_hand() -> None:
    a, b = [10, 20, 30, 30], [30, 40, 50]
    test = mann_whitney(a, b)
    # U of a: the two 30s tie one 30 of b (1/2 each), nothing else in a beats b -> U = 1
    assert test.u == 1.0
    assert test.effect_size == pytest.approx(2 * 1 / 12 - 1)
    # normal approximation with tie correction and continuity correction (what scipy does here)
    n1, n2, n = 4, 3, 7
    sigma = math.sqrt(n1 * n2 / 12 * ((n + 1) - (3 ** 3 - 3) / (n * (n - 1))))
    z = (abs(1.0 - n1 * n2 / 2) - 0.5) / sigma
    assert test.p_value == pytest.approx(math.erfc(z / math.sqrt(2)), rel=1e-9)
    same = mann_whitney([7, 7], [7, 7, 7])
    assert (same.p_value, same.effect_size) == (1.0, 0.0)


def test_runs_that_never_reach_90_count_as_their_budget() -> None:
    def seed(episodes: int | None, budget: int = 100) -> dict:
        return {"episodes_to_90": episodes, "budget": budget}

    faster = compare([seed(10), seed(20), seed(30)], [seed(40), seed(None), seed(None)])
    assert faster["effect_size"] == -1.0 and faster["u"] == 0.0
    # 100 (never) against 40, 100 and 100: U = 1 + 0.5 + 0.5
    tied = compare([seed(None)], [seed(40), seed(None), seed(None)])
    assert tied["u"] == 2.0 and tied["effect_size"] == pytest.approx(2 * 2 / 3 - 1)
    assert compare([], [seed(5)])["p_value"] is None


def test_learning_time_from_the_logs(tmp_path) -> None:
    """Episodes, wall and CPU time to the first evaluation at >= 90 %; an evaluation repeated after
    a resume counts once (the last), each episode's time once (two drones log it twice)."""
    evals = [(5, 0.5, 1.0), (10, 0.95, 2.0), (10, 0.85, 3.0), (15, 0.9, 4.0), (20, 1.0, 5.0)]
    (tmp_path / "evals.jsonl").write_text("".join(
        json.dumps({"after_episodes": n, "success_rate": s, "wall_time_s": w}) + "\n" for n, s, w in evals)
        + "not json\n")
    (tmp_path / "episodes.jsonl").write_text("".join(
        json.dumps({"episode": e, "drone": d, "wall_time_s": 0.5}) + "\n" for e in range(20) for d in (0, 1)))
    times = learning_time(tmp_path)
    assert times["episodes_to_90"] == 15
    assert times["wall_s"] == pytest.approx(15 * 0.5 + 1.0 + 3.0 + 4.0)
    assert times["wall_total_s"] == pytest.approx(20 * 0.5 + 1.0 + 3.0 + 4.0 + 5.0)
    assert times["episodes"] == 20 and times["last_eval_success"] == 1.0
    assert times["cpu_s"] is None and times["cpu_total_s"] is None  # logged before CPU time was recorded
    # CPU time as wall time; one episode logged without it leaves the totals that include it unknown
    (tmp_path / "evals.jsonl").write_text("".join(
        json.dumps({"after_episodes": n, "success_rate": s, "wall_time_s": w, "cpu_time_s": w / 2}) + "\n"
        for n, s, w in evals))
    (tmp_path / "episodes.jsonl").write_text("".join(
        json.dumps({"episode": e, "drone": d, "wall_time_s": 0.5, **({"cpu_time_s": 0.25} if e < 19 else {})})
        + "\n" for e in range(20) for d in (0, 1)))
    times = learning_time(tmp_path)
    assert times["cpu_s"] == pytest.approx((15 * 0.5 + 1.0 + 3.0 + 4.0) / 2)
    assert times["cpu_total_s"] is None and times["wall_total_s"] == pytest.approx(20 * 0.5 + 13.0)
    (tmp_path / "evals.jsonl").write_text(json.dumps({"after_episodes": 5, "success_rate": 0.2}) + "\n")
    assert learning_time(tmp_path)["episodes_to_90"] is None and learning_time(tmp_path)["wall_s"] is None


def test_held_counts_the_seeds_still_at_90_in_their_last_evaluation() -> None:
    def seed(reached: int | None, last: float) -> dict:
        return {"greedy_success": last, "collision_rate": 0.0, "episodes_to_90": reached, "wall_s": 1.0,
                "last_eval_success": last}

    # reached and held; reached and collapsed to 60 %; never reached (not counted either way)
    summary = summarize_seeds([seed(100, 0.95), seed(200, 0.6), seed(None, 0.5)])
    assert (summary["reached_90"], summary["held_90"]) == (2, 1)


def test_trainer_keeps_the_checkpoint_of_its_best_evaluation(tmp_path) -> None:
    from sitl_bridge.rl.common.drones_env import scenario_env_factory
    from sitl_bridge.rl.evaluation.evaluate import EvalResult
    from sitl_bridge.rl.learner.checkpoint import best_checkpoint
    from sitl_bridge.rl.learner.config import load_train_config
    from sitl_bridge.rl.training.run_dir import RunSpec
    from sitl_bridge.rl.training.trainer import Trainer

    config = load_train_config(EMPTY, {"episodes": 3, "eval_every": 0, "eval_episodes": 0, "batch_size": 8,
                                       "layers": 2, "hidden_units": 8})
    with Trainer.start(tmp_path, RunSpec(world=str(EMPTY)), config, scenario_env_factory(EMPTY),
                       progress=False) as trainer:
        assert best_checkpoint(trainer.run_dir) == trainer.run_dir  # none kept yet: the newest is used

        def episode_evaluated_at(success: float) -> int:
            trainer.run_episode()
            trainer.save_checkpoint()
            trainer.evaluator.keep_if_best(EvalResult(str(EMPTY), 1, 1, success, 0.0, 0.0, 0.0, 0.0, 0.0, None))
            return json.loads((trainer.run_dir / "best.json").read_text())["after_episodes"]

        assert episode_evaluated_at(0.5) == 1
        assert episode_evaluated_at(0.25) == 1  # worse: the first stays the best
        assert episode_evaluated_at(0.5) == 1  # a tie (same success and mean reward) keeps the first
        best = trainer.run_dir / "best.safetensors"
        assert best_checkpoint(trainer.run_dir) == best
        assert best.read_bytes() == (trainer.run_dir / "checkpoints" / "ckpt_0000001.safetensors").read_bytes()


# -- the experiment file ---------------------------------------------------------------------------
def _curriculum(folder: Path, worlds: list[Path], name: str = "e_e") -> Path:
    path = folder / f"{name}.yaml"
    stages = "".join(f"    - world: {w}\n" for w in worlds)
    path.write_text(f"curriculum:\n  name: {name}\n  stages:\n{stages}")
    return path


def _experiment(folder: Path, extra: str = "") -> Path:
    curriculum = _curriculum(folder, [EMPTY, EMPTY])
    path = folder / "tiny.yaml"
    path.write_text(f"""experiment:
  name: tiny
  seeds: 0-1
  eval_episodes: 3
  scenarios:
    - world: {EMPTY}
      train: {{episodes: 2, eval_every: 0, eval_episodes: 1, batch_size: 8, layers: 2,
              hidden_units: 8}}
      thesis: {{shorthand: E, result: stable, source: "thesis Table 3"}}
  comparisons:
    - curriculum: {curriculum.name}
      control: true
  report: {{behaviour_episodes: 1, verify_episodes: 1, distill_episodes: 1, distill_iterations: 1,
           picture_episodes: 1, backend_episodes: 1}}
{extra}""")
    return path


def test_shipped_experiments_load() -> None:
    thesis = load_experiment(REPO / "experiments" / "thesis.yaml")
    assert [s.stem for s in thesis.scenarios] == [
        "empty", "random_goal", "obstacle", "random_obstacle", "window", "two_drones_empty", "two_drones_window",
        "random_goal_relative", "window_relative", "two_drones_empty_relative", "two_drones_window_relative",
        "street"]
    assert thesis.seeds == tuple(range(10)) and thesis.eval_episodes == 100
    assert {(c.stems[0], c.target) for c in thesis.comparisons} == {
        ("random_goal_relative", "two_drones_empty_relative"), ("window_relative", "two_drones_window_relative"),
        ("obstacle", "random_obstacle")}
    stems, comparisons = selected(thesis, ["two_drones_empty_relative"])
    assert stems == {"two_drones_empty_relative", "random_goal_relative"}
    assert [c.name for c in comparisons] == ["er_te_relative"]
    assert load_experiment(REPO / "experiments" / "smoke.yaml").seeds == (0, 1)
    every_seed = load_experiment(REPO / "experiments" / "every_seed.yaml")  # its new worlds load and check too
    assert [s.stem for s in every_seed.scenarios][:5] == ["obstacle", "two_blocks", "pillars", "offset_walls", "under_beam"]
    assert all(s.overrides["guided_explore_episodes"] == 100 for s in every_seed.scenarios)


def test_experiment_file_errors_are_one_line(tmp_path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text(f"experiment:\n  scenarios:\n    - world: {EMPTY}\n      train: {{episods: 3}}\n")
    with pytest.raises(ConfigError, match=r"scenarios\[0\]\.train\.episods: unknown key"):
        load_experiment(bad)
    bad.write_text(f"experiment:\n  seeds: 3-1\n  scenarios:\n    - world: {EMPTY}\n")
    with pytest.raises(ConfigError, match="seeds: expected seeds such as 0-9"):
        load_experiment(bad)
    other = _curriculum(tmp_path, [worlds_dir() / "random_goal.yaml", EMPTY], "er_e")
    bad.write_text(f"experiment:\n  scenarios:\n    - world: {EMPTY}\n  comparisons:\n"
                   f"    - curriculum: {other.name}\n")
    with pytest.raises(ConfigError, match="random_goal.yaml is not"):
        load_experiment(bad)
    with pytest.raises(ConfigError, match="--only: expected scenario stems"):
        selected(load_experiment(_experiment(tmp_path)), ["window"])
    # A scenario may have seeds of its own (a baseline), but not one a comparison pairs seed by seed.
    own = worlds_dir() / "random_goal.yaml"
    bad.write_text(f"experiment:\n  seeds: 0-9\n  scenarios:\n    - world: {EMPTY}\n    - world: {own}\n"
                   f"      seeds: 0-2\n")
    experiment = load_experiment(bad)
    assert [experiment.seeds_of(s) for s in experiment.scenarios] == [tuple(range(10)), (0, 1, 2)]
    bad.write_text(bad.read_text() + f"  comparisons:\n    - curriculum: {other.name}\n")
    with pytest.raises(ConfigError, match="seeds: of its own"):
        load_experiment(bad)


# -- end to end ------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> tuple[Path, Path]:
    """A two-seed experiment of two-episode runs on empty.yaml, with an empty -> empty comparison."""
    folder = tmp_path_factory.mktemp("experiment")
    file, out = _experiment(folder), folder / "out"
    assert cli(["experiment", str(file), "--out", str(out), "--workers", "1"]) == 0
    return file, out


def _mtimes(folder: Path) -> dict[str, int]:
    return {str(p.relative_to(folder)): p.stat().st_mtime_ns for p in folder.rglob("*") if p.is_file()}


def test_experiment_end_to_end(finished) -> None:
    file, out = finished
    results = json.loads((out / "results.json").read_text())
    assert set(results) == {"empty", "transfer", "behaviour", "rules", "trees", "backends", "algorithms"}
    empty = results["empty"]
    assert [s["seed"] for s in empty["seeds"]] == [0, 1]
    for seed in empty["seeds"]:
        assert set(seed) >= SEED_KEYS
        assert 0.0 <= seed["greedy_success"] <= 1.0 and 0.0 <= seed["collision_rate"] <= 1.0
        assert seed["episodes"] == 2 and seed["wall_total_s"] > 0
        evaluation = json.loads((out / seed["run_dir"]).parent.joinpath("greedy_eval.json").read_text())
        assert evaluation["result"]["episodes"] == 3
        assert seed["greedy_success"] == evaluation["result"]["success_rate"]
        assert (out / seed["run_dir"] / "best.safetensors").is_file()
    assert empty["success_mean"] == pytest.approx(sum(s["greedy_success"] for s in empty["seeds"]) / 2)
    assert len(empty["success_ci95"]) == 2 and empty["success_ci95"][0] <= empty["success_mean"] <= empty["success_ci95"][1]

    comparison = results["transfer"]["e_e"]
    assert {"with", "without", "test", "p_value", "effect_size"} <= set(comparison)
    assert "Mann-Whitney" in comparison["test"] and 0.0 <= comparison["p_value"] <= 1.0
    assert -1.0 <= comparison["effect_size"] <= 1.0
    assert comparison["without"]["seeds"] == empty["seeds"]
    for seed, plain in zip(comparison["with"]["seeds"], empty["seeds"], strict=True):
        run = json.loads((out / seed["run_dir"] / "run.json").read_text())
        assert run["init_from"] == str((out / plain["run_dir"] / "best.safetensors").resolve())
    # The control runs: from scratch, exploring from the transfer runs' epsilon (the default 0.6).
    control = comparison["control"]
    assert control["epsilon_max"] == 0.6 and [s["seed"] for s in control["seeds"]] == [0, 1]
    assert {"u", "p_value", "effect_size"} <= set(control["with_vs_control"])
    for seed in control["seeds"]:
        assert seed["run_dir"].startswith("runs/control/e_e/empty/seed")
        assert json.loads((out / seed["run_dir"] / "run.json").read_text())["init_from"] is None
        assert yaml.safe_load((out / seed["run_dir"] / "config.yaml").read_text())["epsilon_max"] == 0.6

    report = (out / "RESULTS.md").read_text()
    assert f"sitl-bridge experiment {file} --out {out}" in report
    assert report.count("Not run (") == 0
    for figure in ("figures/empty.png", "figures/transfer_e_e.png", "figures/transfer_e_e_with_runs.png"):
        assert f"({figure})" in report and (out / figure).stat().st_size > 10_000
    meta = json.loads((out / "experiment.json").read_text())
    assert meta["training"][-1]["trained"] == 6 and meta["eval_episodes"] == 3
    assert "| e_e | 0.6 | 2 |" in report  # the control row


def test_resume_trains_only_the_half_finished_run(finished, tmp_path) -> None:
    """Seed 1's plain run was killed during its second episode: no done.json, no checkpoint
    after episode 1, no evaluation yet (only the final one, after episode 2). Only that run
    trains again, from its checkpoint."""
    _, first = finished
    out = tmp_path / "out"
    shutil.copytree(first, out)
    job = out / "runs" / "scenarios" / "empty" / "seed1"
    (run_dir,) = [d for d in job.iterdir() if (d / "run.json").is_file()]
    (job / "done.json").unlink()
    (run_dir / "checkpoints" / "ckpt_0000002.safetensors").unlink()
    for name in ("evals.jsonl", "eval.json", "best.json", "best.safetensors"):
        (run_dir / name).unlink()
    before = _mtimes(out)

    assert cli(["experiment", str(finished[0]), "--out", str(out), "--workers", "1"]) == 0
    after = _mtimes(out)
    changed = {path for path in after if before.get(path) != after[path]}
    runs_changed = {p.split("/seed")[0] + "/seed" + p.split("/seed")[1].split("/")[0] for p in changed
                    if p.startswith("runs/") and "/seed" in p}
    assert runs_changed == {"runs/scenarios/empty/seed1"}  # seed 0 and the transfer runs: untouched
    assert (job / "done.json").is_file()
    episodes = [json.loads(line)["episode"] for line in (run_dir / "episodes.jsonl").read_text().splitlines()]
    assert episodes == [0, 1]  # resumed after episode 1 in the same run directory: no repeat, no gap
    summary = {(r["point"], r["seed"]): r["status"] for r in json.loads((out / "runs" / "summary.json").read_text())}
    assert summary == {("empty", 0): "skipped", ("empty", 1): "done", ("e_e/empty", 0): "skipped",
                       ("e_e/empty", 1): "skipped", ("e_e/control/empty", 0): "skipped",
                       ("e_e/control/empty", 1): "skipped"}
    assert json.loads((out / "experiment.json").read_text())["training"][-1]["trained"] == 1


def test_train_only_leaves_the_report_as_it_is(finished, tmp_path) -> None:
    _, first = finished
    out = tmp_path / "out"
    shutil.copytree(first, out)
    (out / "runs" / "scenarios" / "empty" / "seed1" / "done.json").unlink()
    report = {p: t for p, t in _mtimes(out).items() if not p.startswith("runs/")}

    assert cli(["experiment", str(finished[0]), "--out", str(out), "--workers", "1", "--train-only"]) == 0
    assert (out / "runs" / "scenarios" / "empty" / "seed1" / "done.json").is_file()  # the run was finished
    assert {p: t for p, t in _mtimes(out).items() if p in report} == report  # RESULTS.md, JSON, figures untouched


def test_report_of_a_slimmed_tree_is_the_same_without_flying_again(finished, tmp_path) -> None:
    """tools/slim_results.py on a copy of the results, whose caches were keyed the older way (on
    the checkpoint file's sha256): the report rebuilt from the slim tree gives the same results.json
    and flies nothing again (every cached evaluation, behaviour, rule and tree is reused)."""
    import hashlib
    import subprocess
    import sys

    from sitl_bridge.rl.learner.checkpoint import load_checkpoint
    from sitl_bridge.rl.learner.policy_file import network_digest, online_tensors

    file, first = finished
    out = tmp_path / "out"
    shutil.copytree(first, out)
    for best in out.rglob("best.safetensors"):  # caches as the file-keyed code wrote them
        tensors, state = load_checkpoint(best)
        old, new = hashlib.sha256(best.read_bytes()).hexdigest(), network_digest(online_tensors(tensors), state["network"])
        for cache in out.rglob("*.json"):
            cache.write_text(cache.read_text().replace(new, old))
    runs_bytes = lambda: sum(p.stat().st_size for p in (out / "runs").rglob("*") if p.is_file())  # noqa: E731
    before = runs_bytes()

    slim = subprocess.run([sys.executable, str(REPO / "tools" / "slim_results.py"), str(out)],
                          capture_output=True, text=True, timeout=300)
    assert slim.returncode == 0, slim.stderr
    assert not list(out.rglob("episodes.jsonl")) and not list(out.rglob("checkpoints"))
    assert runs_bytes() < before / 4, (runs_bytes(), before)
    caches = {p: p.read_bytes() for p in out.rglob("*.json") if p.name not in ("results.json", "experiment.json")}

    assert cli(["experiment", str(file), "--out", str(out), "--report-only"]) == 0
    assert json.loads((out / "results.json").read_text()) == json.loads((first / "results.json").read_text())
    assert {p: p.read_bytes() for p in caches} == caches  # nothing flown and cached again
