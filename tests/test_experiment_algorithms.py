"""The report's table of learning algorithms and decision rates, on a tiny real experiment (DQN on
the discrete table and PPO on continuous velocity at a decision period the experiment file sets,
two seeds, a few episodes on `direct`): every number of the table recomputed here from the run
files and from flying each best checkpoint again on the held-out reset seeds through the plain
Gymnasium env (not the report's rollout or measures), and the experiment file's checks."""

from __future__ import annotations

import json
import math
import statistics
from pathlib import Path

import numpy as np
import pytest
import yaml

from sitl_bridge.data_paths import worlds_dir
from sitl_bridge.errors import ConfigError
from sitl_bridge.rl.experiments.runner import load_experiment

pytest.importorskip("scipy")
pytest.importorskip("stable_baselines3")
EPISODES = 3  # held-out greedy episodes per run
PPO_TINY = {"n_steps": 16, "batch_size": 8, "n_epochs": 1, "policy_kwargs": {"net_arch": [8, 8]}}
TRAIN = {"episodes": 3, "eval_every": 1, "eval_episodes": 2, "stop_on_success": 0.0}


def _worlds(folder: Path) -> tuple[Path, Path]:
    """empty.yaml with short episodes, as it is (discrete) and with velocity actions (PPO)."""
    data = yaml.safe_load((worlds_dir() / "empty.yaml").read_text())
    data["task"]["max_steps"] = 8
    data["train"] = {"batch_size": 8, "layers": 1, "hidden_units": 8, "learning_starts": 8}
    discrete = folder / "tiny.yaml"
    discrete.write_text(yaml.safe_dump(data, sort_keys=False))
    data["task"]["action"] = {"type": "velocity", "max_speed_m_s": 2.0, "duration_s": 1.0}
    data["train"] = {"algorithm": "ppo", "ppo": PPO_TINY}
    velocity = folder / "tiny_velocity.yaml"
    velocity.write_text(yaml.safe_dump(data, sort_keys=False))
    return discrete, velocity


def _experiment(folder: Path, arm: str = "action: {duration_s: 0.5}") -> Path:
    discrete, velocity = _worlds(folder)
    path = folder / "compare.yaml"
    path.write_text(f"""experiment:
  name: compare
  seeds: 0-1
  eval_episodes: {EPISODES}
  scenarios:
    - world: {discrete}
      train: {json.dumps(TRAIN)}
      group: E
    - world: {velocity}
      algorithm: ppo
      {arm}
      train: {json.dumps(TRAIN)}
      group: E
""")
    return path


def test_the_experiment_file_declares_arms_and_groups(tmp_path: Path) -> None:
    experiment = load_experiment(_experiment(tmp_path))
    assert [(s.stem, s.action, s.group) for s in experiment.scenarios] == [
        ("tiny", {}, "E"), ("tiny_velocity_ppo_0.5s", {"duration_s": 0.5}, "E")]
    path = _experiment(tmp_path, "action: {duration_s: 0.013}")  # not a multiple of the physics step
    with pytest.raises(ConfigError, match=r"experiment\.scenarios\[1\]\.action\.duration_s: expected a span that "
                                          r"the world's physics step \(\d+ us\) divides, got 0\.013") as error:
        load_experiment(path)
    assert "\n" not in str(error.value)
    with pytest.raises(ConfigError, match=r"experiment\.scenarios\[1\]\.action applied to .*tiny_velocity\.yaml: "
                                          r"task\.action\.frame: expected one of"):
        load_experiment(_experiment(tmp_path, "action: {frame: up}"))
    with pytest.raises(ConfigError, match=r"experiment\.scenarios\[1\]\.action: expected a mapping"):
        load_experiment(_experiment(tmp_path, "action: 1.0"))
    with pytest.raises(ConfigError, match=r"task\.action\.speed_m_s: only with `type: discrete`"):
        load_experiment(_experiment(tmp_path, "action: {speed_m_s: 1.0}"))
    path.write_text(_experiment(tmp_path).read_text().replace("group: E", "group: [E]", 1))
    with pytest.raises(ConfigError, match=r"experiment\.scenarios\[0\]\.group: expected a string"):
        load_experiment(path)


def test_the_shipped_comparison_loads() -> None:
    experiment = load_experiment(Path(__file__).resolve().parents[1] / "experiments" / "continuous.yaml")
    groups: dict[str, list] = {}
    for s in experiment.scenarios:
        groups.setdefault(s.group, []).append((s.overrides.get("algorithm", "dqn"), s.action.get("duration_s")))
    arms = [("dqn", None), ("sac", None), ("sac", 1.0), ("ppo", None), ("ppo", 1.0)]
    assert groups == {"O": arms, "OR": arms, "W": arms, "TE-relative": arms}
    assert experiment.seeds == (0, 1, 2, 3, 4) and experiment.eval_episodes == 100


def _fly(run_dir: Path, seed: int) -> list[dict]:
    """The run's best checkpoint flown greedily on its held-out reset seeds through the plain
    Gymnasium env: outcome, simulated time, path and summed command change per episode."""
    from sitl_bridge.envs import make_env
    from sitl_bridge.rl.evaluation.rollout import eval_seeds
    from sitl_bridge.rl.experiments.seeds import EVAL_SEED_BASE
    from sitl_bridge.rl.learner.policy import policy_from_checkpoint

    policy = policy_from_checkpoint(run_dir)
    env = make_env(run_dir / "scenario.yaml", autopilot="direct")
    flights = []
    try:
        for reset_seed in eval_seeds(EVAL_SEED_BASE + seed, EPISODES):
            obs, info = env.reset(seed=reset_seed)
            start, positions, commands = info["sim_time_s"], [info["position_enu_m"]], []
            while True:
                obs, _, terminated, truncated, info = env.step(policy(np.asarray(obs, dtype=np.float32).reshape(-1)))
                positions.append(info["position_enu_m"])
                commands.append(info["command_enu_m_s"])
                if terminated or truncated:
                    break
            time_s = info["sim_time_s"] - start
            flights.append({"outcome": info["outcome"], "time_s": time_s,
                            "path_m": sum(math.dist(a, b) for a, b in zip(positions[:-1], positions[1:], strict=True)),
                            "change": sum(math.dist(a, b) for a, b in zip(commands[:-1], commands[1:], strict=True)) / time_s})
    finally:
        env.close()
    return flights


def _time_to_90(run_dir: Path) -> tuple[int | None, float | None]:
    evals = {e["after_episodes"]: e for e in map(json.loads, (run_dir / "evals.jsonl").read_text().splitlines())}
    reached = next((n for n in sorted(evals) if evals[n]["success_rate"] >= 0.9), None)
    if reached is None:
        return None, None
    episodes = {}
    for record in map(json.loads, (run_dir / "episodes.jsonl").read_text().splitlines()):
        episodes.setdefault(record["episode"], record)
    return reached, (sum(r["wall_time_s"] for n, r in episodes.items() if n < reached)
                     + sum(e["wall_time_s"] for n, e in evals.items() if n <= reached))


def _median(values: list) -> float | None:
    return statistics.median(values) if values else None


def test_the_table_matches_the_runs_flown_again(tmp_path: Path) -> None:
    from sitl_bridge.rl.experiments import algorithms_section, report
    from sitl_bridge.rl.experiments import results as res
    from sitl_bridge.rl.experiments.runner import run_experiment

    experiment = load_experiment(_experiment(tmp_path))
    out = tmp_path / "out"
    run_experiment(experiment, out, say=lambda _: None)
    results = res.collect(experiment, out, say=lambda _: None)
    assert res.add_sections(results, out, {"algorithms": algorithms_section.add_results_section},
                            settings=experiment.report, say=lambda _: None) == {}
    rows = {r["scenario"]: r for r in results["algorithms"]["E"]}
    assert list(rows) == ["tiny", "tiny_velocity_ppo_0.5s"]

    # the changed action reached the runs: a copy of the world with it, recorded in each run
    derived = yaml.safe_load((out / "runs" / "worlds" / "tiny_velocity_ppo_0.5s.yaml").read_text())
    assert derived["task"]["action"] == {"type": "velocity", "max_speed_m_s": 2.0, "duration_s": 0.5}
    flown: dict[str, list[dict]] = {}
    for stem, algorithm, action, decision in (("tiny", "dqn", "discrete", 1.0),
                                              ("tiny_velocity_ppo_0.5s", "ppo", "velocity", 0.5)):
        row = rows[stem]
        run_dirs = [out / s["run_dir"] for s in results[stem]["seeds"]]
        assert (row["seeds"], row["planned"], len(run_dirs)) == (2, 2, 2)
        for run_dir in run_dirs:
            assert yaml.safe_load((run_dir / "config.yaml").read_text())["algorithm"] == algorithm
            scenario_action = yaml.safe_load((run_dir / "scenario.yaml").read_text())["task"]["action"]
            assert scenario_action.get("type", "discrete") == action and scenario_action["duration_s"] == decision
        assert (row["algorithm"], row["action"], row["decision_s"]) == (algorithm, action, decision)

        flights = {int(d.parent.name.removeprefix("seed")): _fly(d, int(d.parent.name.removeprefix("seed")))
                   for d in run_dirs}
        every = flown[stem] = [f for seed in sorted(flights) for f in flights[seed]]
        for run_dir in run_dirs:  # the section's input, every episode (a row averages the successful ones only)
            held = json.loads((run_dir.parent / "greedy_eval.json").read_text())["episodes"]
            again = flights[int(run_dir.parent.name.removeprefix("seed"))]
            assert [e["outcome"] for e in held] == [f["outcome"] for f in again]
            for e, f in zip(held, again, strict=True):
                assert (e["time_s"], e["path_m"], e["command_change_m_s2"]) == pytest.approx(
                    (f["time_s"], f["path_m"], f["change"]), abs=1e-3)
        wins = [f for f in every if f["outcome"] == "goal"]
        assert (row["drone_episodes"], row["successes"]) == (2 * EPISODES, len(wins))
        p, n, z = len(wins) / len(every), len(every), 1.959963984540054
        centre = (p + z * z / (2 * n)) / (1 + z * z / n)
        half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
        assert row["success"] == pytest.approx(p)
        assert row["success_ci95"] == pytest.approx([max(0.0, centre - half), min(1.0, centre + half)])
        per_seed = {seed: sum(f["outcome"] == "goal" for f in fs) / EPISODES for seed, fs in flights.items()}
        assert {s["seed"]: s["success"] for s in row["seed_success"]} == pytest.approx(per_seed)
        assert row["seeds_90"] == sum(v >= 0.9 for v in per_seed.values())
        for measure, key in (("time_s", "time_to_goal_s"), ("path_m", "path_m"), ("change", "command_change_m_s2")):
            expected = statistics.fmean(f[measure] for f in wins) if wins else None
            assert row[key] == (None if expected is None else pytest.approx(expected, abs=1e-3)), key
        times = [_time_to_90(d) for d in run_dirs]
        reached = [t for t in times if t[0] is not None]
        assert row["reached_90"] == len(reached)
        assert row["episodes_to_90_median"] == _median([t[0] for t in reached])
        assert row["wall_s_median"] == pytest.approx(_median([t[1] for t in reached]))

    # an evaluation cached before the flight measures: kept where no table needs them, else flown again
    seed0 = results["tiny"]["seeds"][0]
    cache = (out / seed0["run_dir"]).parent / "greedy_eval.json"
    record = json.loads(cache.read_text())
    measures = record.pop("episodes")
    cache.write_text(json.dumps(record))
    task = res.EvalTask(str(cache.parent), str(out / seed0["run_dir"]), 0, EPISODES, "direct")
    assert "episodes" not in res.evaluate_run(task)
    res.collect(experiment, out, say=lambda _: None)
    assert json.loads(cache.read_text())["episodes"] == measures

    # the velocity arm commands change between decisions; a seed that flew nothing would hide it
    assert any(f["change"] > 0 for f in flown["tiny_velocity_ppo_0.5s"])
    meta = {"name": "compare", "command": "c", "file": "f", "written": "w", "version": "v", "seeds_text": "0-1",
            "eval_episodes": EPISODES, "report": None}
    text = report.render(results, meta)
    assert "## Learning algorithms and decision rates" in text
    row = rows["tiny_velocity_ppo_0.5s"]
    assert f"| E | `tiny_velocity_ppo_0.5s` | ppo | velocity | 0.5 s | 2/2 | {100 * row['success']:.0f} %" in text


def test_the_sections_built_on_action_codes_skip_a_continuous_scenario(tmp_path: Path) -> None:
    """Behaviour, rules, trees and the grid of typical episodes classify discrete codes: a
    continuous scenario is skipped with the reason, before anything flies (a run directory that
    does not exist is never read), and the discrete one beside it is not."""
    from sitl_bridge.rl.analysis.behaviour import CONTINUOUS_ACTIONS, why_not_classified
    from sitl_bridge.rl.experiments import rules_section, trees_section
    from sitl_bridge.rl.experiments.episode_grid import scenario_grid
    from sitl_bridge.rl.experiments.runner import ReportSettings

    discrete, velocity = _worlds(tmp_path)
    assert (why_not_classified(discrete), why_not_classified(velocity)) == (None, CONTINUOUS_ACTIONS)
    results = {"v": {"world": str(velocity), "seeds": [{"seed": 0, "run_dir": "missing/run"}]}}
    rules_section.add_results_section(results, tmp_path, settings=ReportSettings(), say=lambda _: None)
    assert results["behaviour"]["v"] == {"status": "skipped", "reason": CONTINUOUS_ACTIONS}
    assert results["rules"] == []
    pytest.importorskip("sklearn")
    trees_section.add_results_section(results, tmp_path, settings=ReportSettings(), say=lambda _: None)
    assert results["trees"]["v"] == {"status": "skipped", "reason": CONTINUOUS_ACTIONS}
    with pytest.raises(ValueError, match="continuous velocity actions"):
        scenario_grid("v", results["v"], tmp_path, episodes_per_seed=1, cells=1, seed=0)


def test_the_trained_copy_of_a_world_keeps_its_mesh_files(tmp_path: Path) -> None:
    from sitl_bridge.rl.experiments.runner import trained_world
    from sitl_bridge.world import load_world

    folder = tmp_path / "worlds"
    folder.mkdir()
    corners = [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
    (folder / "cube.obj").write_text("".join(f"v {x} {y} {z}\n" for x, y, z in corners) + "f 1 2 4\nf 5 6 8\n")
    data = yaml.safe_load((worlds_dir() / "empty.yaml").read_text())
    data["world"]["obstacles"] = [{"name": "cube", "shape": "mesh", "file": "cube.obj", "size": [1, 1, 1],
                                   "position": [3, 4, 1]}]
    (folder / "mesh.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    path = tmp_path / "compare.yaml"
    path.write_text(f"experiment:\n  scenarios:\n    - world: {folder / 'mesh.yaml'}\n"
                    "      action: {duration_s: 0.5}\n")
    (scenario,) = load_experiment(path).scenarios
    copy = Path(trained_world(scenario, tmp_path / "out"))
    assert copy == tmp_path / "out" / "runs" / "worlds" / "mesh_0.5s.yaml"
    world = load_world(copy)
    assert world.obstacles[0].shape.mesh_file == str(folder / "cube.obj")
    assert yaml.safe_load(copy.read_text())["task"]["action"]["duration_s"] == 0.5
    written = copy.stat().st_mtime_ns
    assert trained_world(scenario, tmp_path / "out") == str(copy) and copy.stat().st_mtime_ns == written
