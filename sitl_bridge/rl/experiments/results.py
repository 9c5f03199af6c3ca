"""results.json of an experiment: per run a greedy evaluation of its best checkpoint and the
episodes and wall time its periodic evaluations took to reach 90 %, per scenario the mean and
95 % interval over seeds, per comparison a Mann-Whitney U test on episodes to 90 %.

results.json holds one object per scenario keyed by the scenario file's stem (`seeds`: per-seed
`seed`, `greedy_success`, `collision_rate`, `episodes_to_90`, `wall_s`; `success_mean`,
`success_ci95`), `transfer` (per comparison: `with`, `without`, `test`, `p_value`,
`effect_size`, and with `control: true` a `control` summary with its `epsilon_max` and
`with_vs_control`, the same test of with against it), and `rules`, `trees`, `backends` (the policies flown on each autopilot
backend) and `algorithms` (learning algorithms and decision rates per `group:`) when the modules that make them are installed (see `SECTION_HOOKS`). Numbers are plain JSON; an undefined one (no run, one seed) is null.

Definitions (also printed in RESULTS.md):

- greedy success / collision rate: share of drone-episodes that reached the goal / crashed in
  `eval_episodes` greedy episodes of the run's best checkpoint (`best.safetensors`,
  the network of its best periodic evaluation; the newest checkpoint if it kept none), on held-out
  reset seeds `eval_seeds(EVAL_SEED_BASE + seed, n)`: not those of the periodic evaluations that
  chose the checkpoint, the same for the runs with and without transfer of one seed.
- episodes_to_90: episodes trained when a periodic greedy evaluation (`evals.jsonl`, every
  `eval_every` episodes and at the end) first reached 90 % success; null if none did. Its
  resolution is the world's `eval_every`.
- wall_s: wall-clock seconds of training and its greedy evaluations until then (null if never).
- the comparison test uses episodes_to_90 with runs that never reached 90 % counted as their
  episode budget (the most they could have taken; ties at the budget are handled by the test).
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sitl_bridge.cores import core_counter, pin_next_core
from sitl_bridge.rl.common.atomic import atomic_write_json, atomic_write_text
from sitl_bridge.rl.common.episode_files import log_exists, open_log
from sitl_bridge.rl.experiments import (
    algorithms_section,
    backends_section,
    rules_section,
    trees_section,
)
from sitl_bridge.rl.experiments.held_out import EPISODE_MEASURES, GREEDY_FILE, THRESHOLD
from sitl_bridge.rl.experiments.runner import (
    ComparisonSpec,
    Experiment,
    ReportSettings,
    control_epsilon,
    control_root,
    finished,
    job_folder,
    run_of,
    scenario_root,
    stage_folder,
    trained_world,
)
from sitl_bridge.rl.experiments.seeds import EVAL_SEED_BASE
from sitl_bridge.rl.training.run_dir import EPISODES_FILE, EVALS_FILE

log = logging.getLogger(__name__)

TEST_NAME = ("Mann-Whitney U (two-sided) on episodes to 90 % greedy success; runs that never "
             "reached it count as their episode budget")
SectionHook = Callable[..., None]
"""`add_results_section(results: dict, out: Path, *, settings: ReportSettings, say) -> None`."""
SECTION_HOOKS: dict[str, SectionHook] = {
    "rules": rules_section.add_results_section,
    "trees": trees_section.add_results_section,
    "backends": backends_section.add_results_section,
    "algorithms": algorithms_section.add_results_section,
}
"""Sections other modules add: each sets `results[name]` (the rules hook also
`results["behaviour"]`; it may read the runs through each seed's `run_dir`, relative to `out`).
A section that cannot run here (an optional package missing) or fails is left out and reported
as not run."""


# -- one run -------------------------------------------------------------------------------
@dataclass(frozen=True)
class EvalTask:
    """A report evaluation of one run (picklable: it may run in a worker process)."""

    job_dir: str
    run_dir: str
    seed: int
    episodes: int
    autopilot: str
    measures: bool = False
    """The report needs each episode's flight measures (`episodes` in the record): a cached
    evaluation made before they were recorded is flown again."""


def evaluate_run(task: EvalTask) -> dict[str, Any]:
    """Greedy evaluation of the run's best checkpoint on the report's evaluation seeds; cached in
    the job folder, reused while the checkpoint, episodes and seeds are the same. The record:
    `key`, `checkpoint_episode`, `result` (`EvalResult`) and `episodes`, one
    `flight_measures.episode_measures` per drone-episode (absent from records made before it)."""
    from sitl_bridge.rl.learner.checkpoint import best_checkpoint, resolve_checkpoint
    from sitl_bridge.rl.learner.policy_file import network_digest, online_tensors

    checkpoint_file, tensors, state = resolve_checkpoint(best_checkpoint(task.run_dir))
    # the network's digest, not the file's: its policy-only export keeps the cached evaluation
    key = {"checkpoint": checkpoint_file.name, "sha256": network_digest(online_tensors(tensors), state["network"]),
           "episodes": task.episodes, "eval_seed": EVAL_SEED_BASE + task.seed}
    cache = Path(task.job_dir) / GREEDY_FILE
    if cache.is_file():
        try:
            cached = json.loads(cache.read_text())
            if cached.get("key") == key and (EPISODE_MEASURES in cached or not task.measures):
                return cached
        except ValueError:
            pass
    from sitl_bridge.rl.common.drones_env import scenario_env_factory
    from sitl_bridge.rl.evaluation.evaluate import evaluate_policy
    from sitl_bridge.rl.evaluation.flight_measures import episode_measures
    from sitl_bridge.rl.learner.policy import policy_from_checkpoint
    from sitl_bridge.rl.training.run_dir import run_scenario

    world = str(run_scenario(task.run_dir))
    result, traces = evaluate_policy(policy_from_checkpoint(checkpoint_file),
                                     scenario_env_factory(world, task.autopilot),
                                     world=world, episodes=task.episodes, seed=EVAL_SEED_BASE + task.seed)
    record = {"key": key, "checkpoint_episode": int(state.get("episode", 0)), "result": result.to_dict(),
              EPISODE_MEASURES: [episode_measures(t) for t in traces]}
    atomic_write_json(cache, record)
    return record


def evaluate_runs(tasks: list[EvalTask], workers: int) -> list[dict[str, Any]]:
    """Every task's evaluation, in order; in `workers` fresh processes when more than one (each
    on its own core where they fly PX4: `cores.pins_workers`)."""
    if workers <= 1 or len(tasks) <= 1:
        return [evaluate_run(t) for t in tasks]
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    workers = min(workers, len(tasks))
    counter = core_counter(ctx, [task.autopilot for task in tasks], workers)
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=pin_next_core,
                             initargs=(counter,)) as pool:
        return list(pool.map(evaluate_run, tasks))


def _jsonl(path: Path) -> list[dict]:
    rows = []
    if log_exists(path):  # a slimmed run keeps its episode log as .xz
        with open_log(path) as handle:
            text = handle.read().decode(errors="replace")
        for line in text.splitlines():
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    return rows


def learning_time(run_dir: str | Path, threshold: float = THRESHOLD) -> dict[str, Any]:
    """From a run's logs: episodes trained, wall and CPU time when its periodic greedy evaluation
    first reached `threshold` (None if never), the total wall and CPU time and episodes trained,
    and the success of its last periodic evaluation (where training ended: held, or collapsed).
    CPU time is None where a log before then lacks it (runs logged before it was recorded).
    Evaluations repeated after a resume (same episode count) count once, the last one."""
    run_dir = Path(run_dir)
    evals = {int(e["after_episodes"]): e for e in _jsonl(run_dir / EVALS_FILE) if "after_episodes" in e}
    episodes: dict[int, dict] = {}  # a multi-drone episode has one record per drone: the first counts
    for record in _jsonl(run_dir / EPISODES_FILE):
        episodes.setdefault(int(record["episode"]), record)
    reached = next((n for n in sorted(evals) if evals[n]["success_rate"] >= threshold), None)

    def time_until(until: float, cpu: bool) -> float | None:
        key, missing = ("cpu_time_s", None) if cpu else ("wall_time_s", 0.0)
        spent = [r.get(key, missing) for n, r in episodes.items() if n < until]
        spent += [e.get(key, missing) for n, e in evals.items() if n <= until]
        return None if None in spent else math.fsum(map(float, spent))

    last = evals[max(evals)]["success_rate"] if evals else None
    return {"episodes_to_90": reached, "wall_s": None if reached is None else time_until(reached, False),
            "wall_total_s": time_until(math.inf, False),
            "cpu_s": None if reached is None else time_until(reached, True), "cpu_total_s": time_until(math.inf, True),
            "episodes": len(episodes), "last_eval_success": last}


def seed_record(job_dir: Path, seed: int, evaluation: dict[str, Any], out: Path) -> dict[str, Any]:
    """The per-seed object of results.json."""
    from sitl_bridge.rl.training.run_dir import read_run_files

    run_dir = run_of(job_dir)
    assert run_dir is not None
    _, config = read_run_files(run_dir)
    times = learning_time(run_dir)
    result = evaluation["result"]
    return {
        "seed": seed,
        "greedy_success": result["success_rate"],
        "collision_rate": result["crash_rate"],
        "episodes_to_90": times["episodes_to_90"],
        "wall_s": times["wall_s"],
        "wall_total_s": times["wall_total_s"],
        "cpu_s": times["cpu_s"],
        "cpu_total_s": times["cpu_total_s"],
        "episodes": times["episodes"],
        "last_eval_success": times["last_eval_success"],
        "budget": config.episodes,
        "checkpoint_episode": evaluation["checkpoint_episode"],
        "run_dir": _relative(run_dir, out),
    }


def _relative(path: Path, out: Path) -> str:
    try:
        return str(path.resolve().relative_to(out.resolve()))
    except ValueError:
        return str(path)


# -- groups of seeds ------------------------------------------------------------------------
def summarize_seeds(seeds: list[dict[str, Any]]) -> dict[str, Any]:
    """Mean and 95 % t-interval of greedy success over seeds (clipped to [0, 1]), mean collision
    rate, and how many seeds reached 90 % with the median episodes and wall time they took, and
    how many of those were still at 90 % in their last periodic evaluation (`held_90`)."""
    from sitl_bridge.rl.common.stats import mean_ci95

    if not seeds:
        return {"seeds": [], "success_mean": None, "success_ci95": None, "collision_mean": None,
                "reached_90": 0, "held_90": 0, "episodes_to_90_median": None, "wall_s_median": None}
    mean, interval = mean_ci95([s["greedy_success"] for s in seeds])
    reached = [s for s in seeds if s["episodes_to_90"] is not None]
    return {
        "seeds": seeds,
        "success_mean": mean,
        "success_ci95": None if interval is None else [max(0.0, interval[0]), min(1.0, interval[1])],
        "collision_mean": math.fsum(s["collision_rate"] for s in seeds) / len(seeds),
        "reached_90": len(reached),
        "held_90": sum((s.get("last_eval_success") or 0.0) >= THRESHOLD for s in reached),
        "episodes_to_90_median": _median([s["episodes_to_90"] for s in reached]),
        "wall_s_median": _median([s["wall_s"] for s in reached]),
    }


def _median(values: list[float]) -> float | None:
    if not values:
        return None
    ordered = sorted(values)
    mid = len(ordered) // 2
    return float(ordered[mid]) if len(ordered) % 2 else (ordered[mid - 1] + ordered[mid]) / 2


def episodes_to_threshold_or_budget(seeds: list[dict[str, Any]]) -> list[float]:
    """What the comparison test ranks: episodes to 90 %, or the budget for runs that never got there."""
    return [float(s["budget"] if s["episodes_to_90"] is None else s["episodes_to_90"]) for s in seeds]


def compare(with_seeds: list[dict[str, Any]], without_seeds: list[dict[str, Any]]) -> dict[str, Any]:
    """`test`, `p_value`, `effect_size` (rank-biserial: negative = the transfer runs needed fewer
    episodes) of with vs without; null when either side has no finished run."""
    from sitl_bridge.rl.common.stats import mann_whitney

    a, b = episodes_to_threshold_or_budget(with_seeds), episodes_to_threshold_or_budget(without_seeds)
    if not a or not b:
        return {"test": TEST_NAME, "u": None, "p_value": None, "effect_size": None}
    test = mann_whitney(a, b)
    return {"test": TEST_NAME, "u": test.u, "p_value": test.p_value, "effect_size": test.effect_size}


# -- the whole experiment ------------------------------------------------------------------------
def collect(experiment: Experiment, out: str | Path, *, workers: int = 1,
            say: Callable[[str], None] = print) -> dict[str, Any]:
    """results.json's content from the finished runs under `out` (evaluating those not yet
    evaluated); runs not finished are listed per scenario as `unfinished` seeds."""
    out = Path(out)
    folders: dict[tuple[str, str], Path] = {}  # (group, seed) -> job folder; group: stem or comparison
    planned: dict[str, tuple[int, ...]] = {}  # group -> its seeds
    for scenario in experiment.scenarios:
        planned[scenario.stem] = experiment.seeds_of(scenario)
        for seed in planned[scenario.stem]:
            folders[(scenario.stem, str(seed))] = job_folder(scenario_root(out), scenario.stem, seed)
    for comparison in experiment.comparisons:
        for seed in experiment.seeds:
            folders[(f"transfer:{comparison.name}", str(seed))] = stage_folder(
                out, comparison, len(comparison.stems) - 1, seed)
            if comparison.control:
                folders[(f"control:{comparison.name}", str(seed))] = job_folder(
                    control_root(out, comparison.name), comparison.target, seed)
    done = {key: path for key, path in folders.items() if finished(path) and run_of(path) is not None}
    grouped = {s.stem for s in experiment.scenarios if s.group is not None}  # their table needs flight measures
    tasks = {key: EvalTask(str(path), str(run_of(path)), int(key[1]), experiment.eval_episodes, experiment.autopilot,
                           measures=key[0] in grouped)
             for key, path in done.items()}
    say(f"evaluating {len(tasks)} finished runs greedily ({experiment.eval_episodes} episodes each; "
        "cached runs are not evaluated again)")
    evaluations = dict(zip(tasks, evaluate_runs(list(tasks.values()), workers), strict=True))
    records = {key: seed_record(done[key], int(key[1]), evaluations[key], out) for key in done}

    def group(name: str) -> tuple[list[dict[str, Any]], list[int]]:
        wanted = planned.get(name, experiment.seeds)
        seeds = [records[(name, str(s))] for s in wanted if (name, str(s)) in records]
        missing = [s for s in wanted if (name, str(s)) not in records]
        return seeds, missing

    results: dict[str, Any] = {}
    for scenario in experiment.scenarios:
        seeds, missing = group(scenario.stem)
        world = trained_world(scenario, out)
        results[scenario.stem] = {"world": _relative(Path(world), Path.cwd()), **summarize_seeds(seeds),
                                  "unfinished": missing, "thesis": scenario.thesis}
        if scenario.group is not None:
            results[scenario.stem]["group"] = scenario.group
    results["transfer"] = {c.name: _comparison(experiment, c, results, group) for c in experiment.comparisons}
    adjust_transfer_tests(results["transfer"])
    return results


def adjust_transfer_tests(transfer: dict[str, Any]) -> None:
    """Holm-Bonferroni over every test of the comparisons (with vs without, and with vs control
    where there is a control arm): each test gets `p_holm` and `family_tests`, the number of
    tests run (a test not run, p None, is not counted)."""
    from sitl_bridge.rl.common.stats import holm

    tests = [entry for c in transfer.values() for entry in (c, (c.get("control") or {}).get("with_vs_control"))
             if entry is not None]
    family = sum(t.get("p_value") is not None for t in tests)
    for test, adjusted in zip(tests, holm([t.get("p_value") for t in tests]), strict=True):
        test["p_holm"] = adjusted
        test["family_tests"] = family


def _comparison(experiment: Experiment, comparison: ComparisonSpec, results: dict[str, Any],
                group: Callable[[str], tuple[list[dict[str, Any]], list[int]]]) -> dict[str, Any]:
    with_seeds, missing = group(f"transfer:{comparison.name}")
    without = results[comparison.target]
    with_summary = {**summarize_seeds(with_seeds), "unfinished": missing}
    without_summary = {k: v for k, v in without.items() if k not in ("world", "thesis")}
    entry = {"stages": list(comparison.stems), "from": comparison.stems[-2], "to": comparison.target,
             "curriculum": comparison.curriculum, "thesis": comparison.thesis,
             "with": with_summary, "without": without_summary,
             **compare(with_seeds, without["seeds"])}
    if comparison.control:
        control_seeds, control_missing = group(f"control:{comparison.name}")
        entry["control"] = {**summarize_seeds(control_seeds), "unfinished": control_missing,
                            "epsilon_max": control_epsilon(experiment, comparison),
                            "with_vs_control": compare(with_seeds, control_seeds)}
    return entry


def add_sections(results: dict[str, Any], out: str | Path, hooks: dict[str, SectionHook] | None = None, *,
                 settings: ReportSettings | None = None, say: Callable[[str], None] = print) -> dict[str, str]:
    """Run every section hook; returns why some are missing (`{name: reason}`), which RESULTS.md
    reports as not run. A failing hook is reported, not raised: the report of hours of training
    must still be written."""
    missing: dict[str, str] = {}
    for name, hook in (SECTION_HOOKS if hooks is None else hooks).items():
        target = f"{hook.__module__}.{hook.__qualname__}"
        try:
            hook(results, Path(out), settings=settings or ReportSettings(), say=say)
        except Exception as exc:  # noqa: BLE001 - reported in RESULTS.md and on stderr
            log.exception("results section %s failed", name)
            results.pop(name, None)
            missing[name] = f"{target} failed: {type(exc).__name__}: {exc}"
            continue
        if name not in results:
            missing[name] = f"{target} added nothing"
    return missing


def write_json(path: str | Path, data: Any) -> Path:
    """JSON with NaN/inf refused (they are not JSON): a bug shows here, not in a reader."""
    atomic_write_text(path, json.dumps(data, indent=2, allow_nan=False) + "\n")
    return Path(path)
