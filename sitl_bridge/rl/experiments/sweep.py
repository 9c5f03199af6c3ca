"""Sweeps: independent DQN training runs (seeds x a hyperparameter grid), in parallel processes
on this machine or as Ray tasks on a cluster, resumable.

Layout under the sweep root (`--out`, default `runs/sweep__<world>`)::

    <root>/<point>/seed<N>/<world>__<experiment>__<N>__<timestamp>/   one ordinary run directory
    <root>/<point>/seed<N>/done.json                                  written when the run finished
    <root>/summary.json                                               every run's result

`<point>` names the grid point (`base` without a grid, else `lr=0.001,gamma=0.9`). Re-running the
same sweep skips runs with `done.json`, resumes the others from their newest checkpoint
(`Trainer.resume`) and starts those never started. A run that fails is reported with its error;
the others go on.

Vehicle instances (ports 4560+i, ...; only `stub`/`px4` open any): nothing is handed out. Each
run's env claims its own when it starts, from `instance_base` up (`autopilot.allocation`: the
pick is an exclusive lock held until the env closes), so concurrent runs never share one,
whether of this sweep, another sweep or a run by hand. A parent that picked instances for its
workers would have to release them before a worker could lock them, a gap another run could
take; so the parent keeps nothing. px4 envs claim in 0..9 whatever `instance_base` says.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import multiprocessing as mp
import os
import re
import time
import traceback
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from sitl_bridge.cores import core_counter, pin_next_core
from sitl_bridge.errors import ConfigError, load_yaml
from sitl_bridge.lifetime import die_with_parent
from sitl_bridge.rl.learner.config import apply_overrides, load_train_config
from sitl_bridge.rl.training.run_dir import RUN_FILE

DONE_FILE = "done.json"
SUMMARY_FILE = "summary.json"


@dataclass(frozen=True)
class SweepJob:
    """One training run of a sweep."""

    index: int
    world: str
    seed: int
    point: str
    overrides: dict[str, Any]
    autopilot: str
    job_dir: str
    """`<root>/<point>/seed<N>`: holds the run directory and `done.json`."""
    instance_base: int
    """The preferred first vehicle instance of the run's envs (they claim a free block from it up)."""
    progress: bool = False
    watchdog: bool = False
    """Train in a `sitl-bridge train` child supervised by `rl.training.watchdog` (restarted from its last
    checkpoint when it dies or freezes); `direct` only, where no ports are involved."""
    init_from: str | None = None
    """Start the network from this run directory or checkpoint (`train --init-from`): the
    transfer runs of an incremental-complexity comparison."""


@dataclass
class SweepResult:
    """What became of one run (a row of the summary)."""

    point: str
    seed: int
    status: str
    """`done` (trained this time), `skipped` (finished before), `failed`."""
    run_dir: str = ""
    episodes: int = 0
    global_step: int = 0
    success_rate: float = 0.0
    greedy_success: float | None = None
    wall_s: float = 0.0
    error: str = ""
    restarts: int = 0
    """Times the watchdog restarted the run (`--watchdog`)."""
    extra: dict[str, Any] = field(default_factory=dict)


def parse_seeds(text: str) -> list[int]:
    """`0-9`, `3`, `0,2,5-7` -> sorted unique seeds."""
    seeds: set[int] = set()
    for part in text.split(","):
        match = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", part)
        if not match:
            raise ConfigError(f"command line: --seeds: expected e.g. 0-9 or 0,3,5-7, got {text!r}")
        low, high = int(match[1]), int(match[2] or match[1])
        if high < low:
            raise ConfigError(f"command line: --seeds: range {part.strip()!r} runs backwards")
        seeds.update(range(low, high + 1))
    return sorted(seeds)


def load_grid(path: str | Path | None, world: str | Path) -> list[tuple[str, dict[str, Any]]]:
    """Grid points `(name, overrides)`: the cartesian product of a YAML mapping
    `{hyperparameter: [values]}` (each checked against the world's train config), or one
    point `base` without a grid."""
    if path is None:
        return [("base", {})]
    root = load_yaml(path)
    if not isinstance(root.value, dict) or not root.value:
        raise ConfigError(f"{path}: expected a mapping of hyperparameter: [values], got {root.value!r}")
    names, values = [], []
    for name, node_values in root.value.items():
        options = node_values if isinstance(node_values, list) else [node_values]
        if not options:
            raise ConfigError(f"{path}: {name}: expected a non-empty list of values, got []")
        names.append(str(name))
        values.append(options)
    base = load_train_config(world)
    points = []
    for combo in itertools.product(*values):
        overrides = dict(zip(names, combo, strict=True))
        try:
            apply_overrides(base, overrides)
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}") from None
        points.append((",".join(f"{k}={v}" for k, v in overrides.items()), overrides))
    return points


def plan(world: str | Path, seeds: Iterable[int], points: list[tuple[str, dict[str, Any]]], root: str | Path,
         *, autopilot: str = "direct", instance_base: int = 0, common: dict[str, Any] | None = None,
         watchdog: bool = False) -> list[SweepJob]:
    """Every (grid point, seed) run of the sweep, in a stable order (each point's settings
    checked first: a bad one is a ConfigError now, not a failed run later)."""
    for _, overrides in points:
        load_train_config(world, {**(common or {}), **overrides})
    jobs = []
    for point, overrides in points:
        for seed in seeds:
            job_dir = Path(root) / _safe(point) / f"seed{seed}"
            jobs.append(SweepJob(len(jobs), str(world), seed, point, {**(common or {}), **overrides}, autopilot,
                                 str(job_dir), instance_base, watchdog=watchdog))
    return jobs


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.=,+-]", "_", name)


def run_job(job: SweepJob) -> SweepResult:
    """Train one run to its end (or resume it); never raises: a failure is a result."""
    job_dir = Path(job.job_dir)
    done = job_dir / DONE_FILE
    if done.exists():
        result = SweepResult(**json.loads(done.read_text()))
        result.status = "skipped"
        return result
    start = time.perf_counter()
    result = SweepResult(job.point, job.seed, "failed")
    try:
        result = _train(job)
        result.wall_s = time.perf_counter() - start
        tmp = done.with_suffix(".tmp")
        tmp.write_text(json.dumps(asdict(result), indent=1) + "\n")
        tmp.replace(done)  # atomic: a half-written done.json never marks a run finished
    except BaseException as exc:  # a failed run is a result; KeyboardInterrupt included (the pool stops)
        result.error = f"{type(exc).__name__}: {exc}"
        result.extra["traceback"] = traceback.format_exc(limit=8)
        result.wall_s = time.perf_counter() - start
        if not isinstance(exc, Exception):
            raise
    return result


def _train(job: SweepJob) -> SweepResult:
    if job.watchdog:
        return _train_supervised(job)
    from sitl_bridge.rl.common.drones_env import scenario_env_factory
    from sitl_bridge.rl.training.run_dir import RunSpec
    from sitl_bridge.rl.training.runs import resume_run, start_run

    job_dir = Path(job.job_dir)
    job_dir.mkdir(parents=True, exist_ok=True)
    factory = scenario_env_factory(job.world, job.autopilot, instance_base=job.instance_base)
    started = [d for d in sorted(job_dir.iterdir()) if (d / RUN_FILE).exists()]
    if started:  # an unfinished run of an earlier sweep: continue it
        trainer = resume_run(started[-1], factory, episodes=job.overrides.get("episodes"),
                                 progress=job.progress)
    else:
        config = load_train_config(job.world, job.overrides)
        spec = RunSpec(world=job.world, autopilot=job.autopilot, seed=job.seed, init_from=job.init_from)
        trainer = start_run(job_dir, spec, config, factory, progress=job.progress)
    with trainer:
        outcome = trainer.train()
        greedy = trainer.last_eval.success_rate if trainer.last_eval is not None else None
        # As `train` does: the network at the end of the budget is evaluated (periodic
        # evaluations stop before the last episode); one that stopped early was just evaluated.
        if (outcome.episodes >= trainer.config.episodes and trainer.config.eval_episodes > 0
                and not trainer.stopped_early):
            greedy = (trainer.recorded_evaluation() or trainer.evaluate()).success_rate  # not again after a kill
    return SweepResult(job.point, job.seed, "done", str(outcome.run_dir), outcome.episodes,
                       outcome.global_step, outcome.success_rate, greedy)


def _train_supervised(job: SweepJob) -> SweepResult:
    """The run as `sitl-bridge train` under the watchdog; its result read back from the run dir."""
    from sitl_bridge.rl.common.episode_log import read_records
    from sitl_bridge.rl.training.run_dir import EPISODES_FILE, EVAL_FILE
    from sitl_bridge.rl.training.watchdog import Watchdog

    job_dir = Path(job.job_dir)
    job_dir.mkdir(parents=True, exist_ok=True)
    started = [d for d in sorted(job_dir.iterdir()) if (d / RUN_FILE).exists()]
    episodes = job.overrides.get("episodes")
    if started:
        argv = ["--resume", str(started[-1]), *([] if episodes is None else ["--episodes", str(episodes)])]
    else:
        argv = [job.world, "--seed", str(job.seed), "--out", str(job_dir), "--autopilot", job.autopilot]
        if job.init_from:
            argv += ["--init-from", job.init_from]
        for name, value in job.overrides.items():
            flag = "--" + name.replace("_", "-")
            argv += [flag if value else "--no-" + flag[2:]] if isinstance(value, bool) else [flag, str(value)]
    argv.append("--no-progress")
    report = Watchdog(argv).run()
    if report.exit_code != 0 or report.run_dir is None:
        raise RuntimeError(report.gave_up or f"training exited with code {report.exit_code}")
    records = read_records(report.run_dir / EPISODES_FILE)
    eval_path = report.run_dir / EVAL_FILE
    greedy = json.loads(eval_path.read_text())["success_rate"] if eval_path.exists() else None
    recent = records[-100:]
    return SweepResult(job.point, job.seed, "done", str(report.run_dir),
                       1 + max((r["episode"] for r in records), default=-1),
                       max((r.get("global_step", 0) for r in records), default=0),
                       sum(r["outcome"] == "goal" for r in recent) / max(len(recent), 1), greedy,
                       restarts=len(report.restarts))


# -- local processes ------------------------------------------------------------------------
def _init_worker(core_counter: Any = None) -> None:
    """End this worker process with the sweep (a killed sweep must not leave runs training on
    with nobody to collect them); with a counter, pin it to its own core (`cores`)."""
    die_with_parent()
    pin_next_core(core_counter)


def run_local(jobs: list[SweepJob], workers: int,
              on_result: Callable[[SweepResult], None] | None = None) -> list[SweepResult]:
    """Run `jobs` in `workers` fresh processes, each on its own core where the runs fly PX4
    (`cores.pins_workers`); results in job order."""
    ctx = mp.get_context("spawn")  # fresh interpreters: no pybullet/torch state inherited
    results: dict[int, SweepResult] = {}
    workers = max(1, workers)
    counter = core_counter(ctx, [job.autopilot for job in jobs], workers) if jobs else None
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_init_worker,
                             initargs=(counter,)) as pool:
        futures = {pool.submit(run_job, job): job for job in jobs}
        for future in as_completed(futures):
            job = futures[future]
            try:
                result = future.result()
            except Exception as exc:  # the worker process itself died
                result = SweepResult(job.point, job.seed, "failed", error=f"worker died: {type(exc).__name__}: {exc}")
            results[job.index] = result
            if on_result is not None:
                on_result(result)
    return [results[job.index] for job in jobs]


def run_serial(jobs: list[SweepJob], on_result: Callable[[SweepResult], None] | None = None) -> list[SweepResult]:
    """Run `jobs` one after another in this process (one worker: no process to start)."""
    results = []
    for job in jobs:
        results.append(run_job(job))
        if on_result is not None:
            on_result(results[-1])
    return results


# -- Ray ------------------------------------------------------------------------------------
RAY_WORKER_NICENESS = "RAY_worker_niceness"
"""Ray's setting (an environment variable) of how many nice levels below the raylet its workers
run: 15 by default."""


@contextlib.contextmanager
def _local_cluster_env() -> Iterator[None]:
    """Around `ray.init`: a local cluster started here runs its workers at the sweep's own
    priority (RAY_worker_niceness 0, unless the user set it). Ray's +15 keeps its daemons
    responsive, but a sweep's tasks are the work: on a busy machine a task at +15 gets a small
    fraction of the CPU of any process at the sweep's priority (two 2-episode runs beside two
    busy processes: tasks about 100 s instead of 30 s; the test of this backend ran into its
    300 s limit at load 3-6)."""
    unset = RAY_WORKER_NICENESS not in os.environ
    if unset:
        os.environ[RAY_WORKER_NICENESS] = "0"
    try:
        yield
    finally:
        if unset:
            os.environ.pop(RAY_WORKER_NICENESS, None)


def run_ray(jobs: list[SweepJob], address: str | None = None, num_cpus_per_run: float = 1.0,
            on_result: Callable[[SweepResult], None] | None = None) -> list[SweepResult]:
    """Run `jobs` as Ray tasks: Ray's local cluster by default, `address` for an existing one
    (`ray start --head` on one machine, `ray start --address HEAD:6379` on the others; the
    sweep root must be a path every node shares). Ray schedules; nothing here does."""
    try:
        import ray
    except ImportError:
        raise ConfigError("command line: --backend ray: Ray is not installed (pip install 'sitl-bridge[ray]')") from None
    started_here = not ray.is_initialized()
    if started_here:
        # read by the processes a local cluster starts; a cluster at `address` keeps its own setting
        with _local_cluster_env():
            # "local": a cluster of its own, as documented; Ray's default (None) would join one
            # named in RAY_ADDRESS or left running by `ray start` (`--address auto` asks for that)
            ray.init(address=address or "local", include_dashboard=False, log_to_driver=False)
    try:
        task = ray.remote(num_cpus=num_cpus_per_run)(run_job)
        refs = {task.remote(job): job for job in jobs}
        results: dict[int, SweepResult] = {}
        pending = list(refs)
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            job = refs[ready[0]]
            try:
                result = ray.get(ready[0])
            except Exception as exc:  # the task's process died (a run's own errors come back as results)
                result = SweepResult(job.point, job.seed, "failed", error=f"ray task died: {type(exc).__name__}: {exc}")
            results[job.index] = result
            if on_result is not None:
                on_result(result)
        return [results[job.index] for job in jobs]
    finally:
        if started_here:
            ray.shutdown()


# -- summary --------------------------------------------------------------------------------
def summary_table(results: list[SweepResult]) -> str:
    """One line per run, then per grid point the median success over its seeds."""
    lines = [f"{'point':<28} {'seed':>4} {'status':<8} {'episodes':>8} {'steps':>8} {'rolling':>7} "
             f"{'greedy':>6} {'wall s':>7}  run dir / error"]
    for r in results:
        greedy = "-" if r.greedy_success is None else f"{r.greedy_success:.0%}"
        where = r.error if r.status == "failed" else r.run_dir
        lines.append(f"{r.point[:28]:<28} {r.seed:>4} {r.status:<8} {r.episodes:>8} {r.global_step:>8} "
                     f"{r.success_rate:>7.0%} {greedy:>6} {r.wall_s:>7.1f}  {where}")
    by_point: dict[str, list[SweepResult]] = {}
    for r in results:
        by_point.setdefault(r.point, []).append(r)
    for point, rows in by_point.items():
        ok = [r for r in rows if r.status != "failed"]
        greedy = sorted(r.greedy_success for r in ok if r.greedy_success is not None)
        median = f"{greedy[len(greedy) // 2]:.0%}" if greedy else "-"
        lines.append(f"{point}: {len(ok)}/{len(rows)} runs finished, median greedy success {median}")
    return "\n".join(lines)


def write_summary(root: str | Path, results: list[SweepResult]) -> Path:
    path = Path(root) / SUMMARY_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    rows = [{k: v for k, v in asdict(r).items() if k != "extra"} for r in results]
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(rows, indent=1) + "\n")
    tmp.replace(path)
    return path
