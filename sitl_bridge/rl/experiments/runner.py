"""Experiments: every scenario of a list across seeds, and incremental-complexity comparisons,
trained through the sweep machinery (`rl.experiments.sweep`: local processes or Ray), resumable.

An experiment file (`experiments/thesis.yaml`)::

    experiment:
      name: thesis
      seeds: 0-9                      # or a list of integers
      eval_episodes: 100              # greedy episodes per run for the reported rates
      scenarios:
        - world: ../worlds/random_goal.yaml
          train: {episodes: 1500}     # overrides of that world's train: section (the budget)
          algorithm: ppo              # optional: dqn, ppo, sac or td3 (its key is then `<stem>_ppo`,
                                      # so one world can be listed once per algorithm)
          action: {duration_s: 1.0}   # optional: changes of the world's task.action (its key gets
                                      # `_1s`; other keys `_<key>-<value>`); trained on a copy
                                      # of the world with them, `DIR/runs/worlds/<key>.yaml`
          group: ER                   # optional: its row group in the table comparing learning
                                      # algorithms and decision rates (`algorithms_section`)
          seeds: 0-2                  # optional: its own seeds (a baseline), not in a comparison
          thesis: {shorthand: ER, result: "stable", source: "thesis Table 3"}   # shown beside ours
      comparisons:                    # with vs without the earlier network, same seeds
        - curriculum: ../worlds/curricula/er_te.yaml
          thesis: {result: "about as many episodes with as without", source: "thesis 7.2"}
          control: true               # also from scratch, exploring from the transfer runs' epsilon
      report: {behaviour_episodes: 10, backend_episodes: 10}   # the report's own flights (`ReportSettings`)

World and curriculum paths are relative to the current directory, or else to the experiment
file. A comparison's curriculum names scenarios of the list in order; its first stage's runs are
the plain runs of that scenario, each later stage trains again, seed by seed, from the previous
stage's run of the same seed (its best checkpoint, `--init-from`), with the scenario's overrides
and then the stage's. The last stage's transfer runs are compared with the plain runs of that
scenario. A transfer run starts exploring at its `transfer_epsilon_max` (the thesis: 0.45-0.8),
the plain run at `epsilon_max` (1.0), so the two differ in more than the network; with `control:
true` the target is also trained from scratch starting at the transfer runs' epsilon (the
control runs), which separates what the earlier network gives from what less exploration gives.

Layout under `--out DIR`::

    DIR/runs/scenarios/<stem>/seed<N>/<run dir>, done.json      plain runs (sweep job folders)
    DIR/runs/transfer/<comparison>/<stem>/seed<N>/...           transfer runs
    DIR/runs/control/<comparison>/<stem>/seed<N>/...            control runs (`control: true`)
    DIR/runs/summary.json                                       the last invocation's sweep results
    DIR/runs/invocations.jsonl                                  every invocation: workers, counts

Re-running the same command skips finished runs (`done.json`), resumes unfinished ones from their
newest checkpoint and starts the rest (the sweep's own rules).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sitl_bridge.errors import ConfigError, Node, load_yaml
from sitl_bridge.rl.experiments import sweep
from sitl_bridge.rl.learner.config import load_train_config, parse_train_node
from sitl_bridge.rl.training.run_dir import RUN_FILE

RESERVED = frozenset({"transfer", "rules", "behaviour", "trees", "backends", "algorithms"})
"""Top-level keys of results.json that are not scenarios."""
INVOCATIONS_FILE = "invocations.jsonl"
"""`DIR/runs/invocations.jsonl`: one line per training invocation (workers, backend, --only, counts)."""
THESIS_KEYS = frozenset({"shorthand", "result", "runs", "behaviour", "source"})
"""What the thesis reported per scenario (free text), shown beside our figures."""


@dataclass(frozen=True)
class ScenarioSpec:
    """One scenario of an experiment: trained once per seed."""

    world: str
    """Absolute path of the scenario file."""
    stem: str
    """The file's stem: the scenario's key in results.json."""
    overrides: dict[str, Any]
    """Overrides of the world's `train:` section (e.g. the episodes budget)."""
    thesis: dict[str, str] = field(default_factory=dict)
    seeds: tuple[int, ...] | None = None
    """Its own seeds (e.g. fewer for a baseline), else the experiment's."""
    action: dict[str, Any] = field(default_factory=dict)
    """Changes of the world's `task.action` (e.g. the decision period): trained on a copy of the
    world with them (`trained_world`)."""
    group: str | None = None
    """Its row group in the learning-algorithm and decision-rate table (None: not in it)."""


@dataclass(frozen=True)
class ComparisonSpec:
    """Incremental complexity: the stages of a curriculum, each trained from the previous one."""

    name: str
    stems: tuple[str, ...]
    """Scenario stems in curriculum order (at least two)."""
    stage_overrides: tuple[dict[str, Any], ...]
    """Each stage's own `train:` overrides (applied after the scenario's)."""
    curriculum: str
    thesis: dict[str, str] = field(default_factory=dict)
    control: bool = False
    """Also train the target from scratch with the transfer runs' starting epsilon."""

    @property
    def target(self) -> str:
        """The scenario whose runs with and without the earlier network are compared."""
        return self.stems[-1]


@dataclass(frozen=True)
class ReportSettings:
    """How much the report step flies besides the greedy evaluation (the experiment file's
    optional `report:` section; these defaults keep it to minutes per scenario)."""

    behaviour_episodes: int = 10
    """Greedy episodes per seed classified for the behaviour analysis and the candidate rules."""
    verify_episodes: int = 20
    """Episodes a scenario's rules YAML flies in each scenario it is verified in."""
    distill_episodes: int = 50
    """Episodes per DAgger iteration of the distillation, and of the tree-vs-network comparison
    (20 leave a rare manoeuvre, TE's dive under the other drone, with too few states to fit, and a 5-point gap in
    one failed episode)."""
    distill_iterations: int = 5
    """DAgger iterations (trees fitted and scored)."""
    distill_depth: int = 6
    """Deepest distilled tree allowed."""
    picture_episodes: int = 2
    """Greedy episodes per seed flown for the grid of typical episodes."""
    picture_cells: int = 6
    """Most episodes (one per behaviour, most common first) in a scenario's grid."""
    backend_episodes: int = 10
    """Greedy episodes per seed flown on each autopilot backend for the transfer table."""
    backend_seeds: int = 0
    """How many finished seeds (the lowest) the backend table flies; 0: all of them."""


@dataclass(frozen=True)
class Experiment:
    name: str
    source: str
    seeds: tuple[int, ...]
    eval_episodes: int
    scenarios: tuple[ScenarioSpec, ...]
    comparisons: tuple[ComparisonSpec, ...]
    autopilot: str = "direct"
    report: ReportSettings = field(default_factory=ReportSettings)

    def scenario(self, stem: str) -> ScenarioSpec:
        return next(s for s in self.scenarios if s.stem == stem)

    def seeds_of(self, scenario: ScenarioSpec) -> tuple[int, ...]:
        """The seeds `scenario` trains on: its own `seeds:`, else the experiment's."""
        return self.seeds if scenario.seeds is None else scenario.seeds


def load_experiment(path: str | Path) -> Experiment:
    """Parse and check an experiment file (worlds, train overrides, curricula and their input
    sizes) before anything trains; errors are one-line ConfigErrors naming the key."""
    from sitl_bridge.rl.training.curriculum import load_curriculum, world_path

    base = Path(path).parent
    root = load_yaml(path)
    root.reject_unknown({"experiment"})
    node = root.get("experiment")
    node.reject_unknown({"name", "seeds", "eval_episodes", "autopilot", "scenarios", "comparisons", "report"})
    scenarios: list[ScenarioSpec] = []
    for item in node.get("scenarios").list(min_len=1):
        item.reject_unknown({"world", "train", "thesis", "seeds", "algorithm", "action", "group"})
        world = str(Path(world_path(item.get("world"), base)).resolve())
        train = item.get("train", None)
        overrides = dict(train.value or {})
        if item.has("algorithm"):  # the same world may be listed once per algorithm
            overrides["algorithm"] = item.get("algorithm").string()
        config = parse_train_node(Node(overrides, train.source, train.path), load_train_config(world))
        # (a typo fails now, not after hours)
        stem = Path(world).stem + (f"_{config.algorithm}" if item.has("algorithm") and config.algorithm != "dqn" else "")
        action = _action_changes(item.get("action"), world) if item.has("action") else {}
        stem += "".join(_action_suffix(key, value) for key, value in action.items())
        if stem in RESERVED or any(s.stem == stem for s in scenarios):
            raise item.get("world").error(f"a scenario whose key (file stem, algorithm, action changes) is "
                                          f"unique and not one of {', '.join(sorted(RESERVED))}")
        seeds = tuple(_seeds(item.get("seeds"))) if item.has("seeds") else None
        group = item.get("group").string() if item.has("group") else None
        scenarios.append(ScenarioSpec(world, stem, overrides, _thesis(item.get("thesis", {})), seeds, action, group))
    by_world = {s.world: s.stem for s in scenarios if not s.action}  # a curriculum names unchanged worlds
    comparisons: list[ComparisonSpec] = []
    for item in node.get("comparisons", []).list():
        item.reject_unknown({"curriculum", "thesis", "control"})
        file_node = item.get("curriculum")
        file = _existing(file_node, base)
        curriculum = load_curriculum(file)  # checks that every stage's network fits the next
        stems = []
        for stage in curriculum.stages:
            stem = by_world.get(str(Path(stage.world).resolve()))
            if stem is None:
                raise file_node.error(f"a curriculum whose worlds are all scenarios of this experiment "
                                      f"({stage.world} is not)")
            stems.append(stem)
        if len(stems) < 2 or any(c.name == curriculum.name for c in comparisons):
            raise file_node.error("a curriculum of at least two stages, with a name no other comparison has")
        if any(s.seeds is not None for s in scenarios if s.stem in stems):
            raise file_node.error("a curriculum of scenarios on the experiment's seeds (a comparison pairs them "
                                  "seed by seed; one of its scenarios has seeds: of its own)")
        comparisons.append(ComparisonSpec(curriculum.name, tuple(stems),
                                          tuple(dict(s.overrides) for s in curriculum.stages), file,
                                          _thesis(item.get("thesis", {})), item.get("control", False).boolean()))
    return Experiment(
        name=node.get("name", Path(path).stem).string(),
        source=str(path),
        seeds=tuple(_seeds(node.get("seeds", "0-9"))),
        eval_episodes=node.get("eval_episodes", 100).integer(minimum=1, maximum=100_000),
        scenarios=tuple(scenarios),
        comparisons=tuple(comparisons),
        autopilot=node.get("autopilot", "direct").string(("direct", "stub", "px4")),
        report=_report_settings(node.get("report", {})),
    )


def _report_settings(node: Node) -> ReportSettings:
    names = [f.name for f in dataclasses.fields(ReportSettings)]
    node.reject_unknown(set(names))
    limits = {"distill_depth": 12}
    lowest = {"backend_seeds": 0}  # 0: every seed
    return ReportSettings(**{name: child.integer(minimum=lowest.get(name, 1), maximum=limits.get(name, 10_000))
                             for name, child in node.items()})


def _seeds(node: Node) -> list[int]:
    if isinstance(node.value, str):
        try:
            return sweep.parse_seeds(node.value)
        except ConfigError:
            raise node.error("seeds such as 0-9 or 0,3,5-7, or a list of integers") from None
    seeds = sorted({item.integer(minimum=0) for item in node.list(min_len=1)})
    return seeds


def _action_changes(node: Node, world: str) -> dict[str, Any]:
    """A scenario's `action:` changes, checked merged into its world's `task.action` now (a
    decision period that is no multiple of the physics step fails here, not in a training run)."""
    from sitl_bridge.envs.scenario import limits_of
    from sitl_bridge.envs.task import parse_task
    from sitl_bridge.world import load_world
    from sitl_bridge.world.clock import divides
    from sitl_bridge.world.loader import TASK_SPANS_S

    if not isinstance(node.value, dict) or not node.value:
        raise node.error("a mapping of task.action keys to change (e.g. {duration_s: 1.0})")
    changes = dict(node.value)
    loaded = load_world(world)
    task = parse_task(Node(_changed_task(world, changes), f"{node.source}: {node.path} applied to {world}", "task"),
                      limits_of(loaded))
    for section, key, _ in TASK_SPANS_S:  # flown as whole physics steps on every backend
        value = getattr(getattr(task, section), key)
        if key in changes and value > 0 and not divides(loaded.physics.step_us, value):
            raise node.get(key).error(f"a span that the world's physics step ({loaded.physics.step_us} us) divides")
    return changes


def _changed_task(world: str, changes: dict[str, Any]) -> dict[str, Any]:
    task = dict(load_yaml(world).value.get("task") or {})
    task["action"] = {**(task.get("action") or {}), **changes}
    return task


def _action_suffix(key: str, value: Any) -> str:
    """`duration_s: 1.0` -> `_1s`; any other change -> `_<key>-<value>`."""
    if key == "duration_s" and isinstance(value, (int, float)):
        return f"_{value:g}s"
    return f"_{key}-{value}".replace("/", "-").replace(" ", "")


def trained_world(scenario: ScenarioSpec, out: str | Path) -> str:
    """The scenario file `scenario` trains on: its world, or with `action:` changes a copy of
    the world with them, `out/runs/worlds/<stem>.yaml` (written when missing or different)."""
    if not scenario.action:
        return scenario.world
    import yaml

    from sitl_bridge.rl.common.atomic import atomic_write_text

    path = Path(out) / "runs" / "worlds" / f"{scenario.stem}.yaml"
    data = _rebased(dict(load_yaml(scenario.world).value), Path(scenario.world).parent, path.parent)
    data["task"] = _changed_task(scenario.world, scenario.action)
    text = (f"# {Path(scenario.world).name} with task.action changed by an experiment: {scenario.action}\n"
            "# (written by `sitl-bridge experiment`; edit the experiment file, not this copy)\n"
            + yaml.safe_dump(data, sort_keys=False))
    if not path.is_file() or path.read_text() != text:
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path, text)
    return str(path)


def _rebased(value: Any, source: Path, target: Path) -> Any:
    """`value` with every relative `file:` (an obstacle's mesh, relative to its world file) made
    relative to `target`, where the copy of the world is written."""
    if isinstance(value, list):
        return [_rebased(v, source, target) for v in value]
    if not isinstance(value, dict):
        return value
    rebased = {k: _rebased(v, source, target) for k, v in value.items()}
    if isinstance(rebased.get("file"), str) and not Path(rebased["file"]).is_absolute():
        rebased["file"] = os.path.relpath((source / rebased["file"]).resolve(), Path(target).resolve())
    return rebased


def _thesis(node: Node) -> dict[str, str]:
    node.reject_unknown(THESIS_KEYS)
    return {key: child.string() for key, child in node.items()}


def _existing(node: Node, base: Path) -> str:
    for candidate in (Path(node.string()), base / node.string()):
        if candidate.is_file():
            return os.path.normpath(candidate)
    raise node.error("an existing file (relative to the current directory or to this file)")


# -- layout -------------------------------------------------------------------------------
def scenario_root(out: str | Path) -> Path:
    return Path(out) / "runs" / "scenarios"


def transfer_root(out: str | Path, comparison: str) -> Path:
    return Path(out) / "runs" / "transfer" / comparison


def control_root(out: str | Path, comparison: str) -> Path:
    return Path(out) / "runs" / "control" / comparison


def job_folder(root: Path, stem: str, seed: int) -> Path:
    """Where the sweep keeps one run of `stem` and its `done.json` (`sweep.plan`'s layout)."""
    return root / stem / f"seed{seed}"


def run_of(job_dir: str | Path) -> Path | None:
    """The run directory inside a sweep job folder (the newest, as the sweep resumes it)."""
    job_dir = Path(job_dir)
    if not job_dir.is_dir():
        return None
    started = [d for d in sorted(job_dir.iterdir()) if (d / RUN_FILE).is_file()]
    return started[-1] if started else None


def finished(job_dir: str | Path) -> bool:
    """The sweep wrote `done.json`: the run trained its whole budget (or stopped on success)."""
    return (Path(job_dir) / sweep.DONE_FILE).is_file()


def stage_folder(out: str | Path, comparison: ComparisonSpec, stage: int, seed: int) -> Path:
    """Job folder of stage `stage` of a comparison: stage 0 is the plain run of its scenario."""
    if stage == 0:
        return job_folder(scenario_root(out), comparison.stems[0], seed)
    return job_folder(transfer_root(out, comparison.name), comparison.stems[stage], seed)


# -- running ------------------------------------------------------------------------------
def selected(experiment: Experiment, only: Iterable[str] | None) -> tuple[set[str], list[ComparisonSpec]]:
    """Scenario stems to train and comparisons to run for `--only` (None: everything). A
    comparison runs when its target is named; the scenarios it starts from are trained too."""
    known = {s.stem for s in experiment.scenarios}
    if only is None:
        return known, list(experiment.comparisons)
    wanted = set(only)
    unknown = sorted(wanted - known)
    if unknown:
        raise ConfigError(f"command line: --only: expected scenario stems of {experiment.source} "
                          f"({', '.join(sorted(known))}), got {', '.join(unknown)}")
    comparisons = [c for c in experiment.comparisons if c.target in wanted]
    return wanted | {stem for c in comparisons for stem in c.stems[:-1]}, comparisons


def run_experiment(experiment: Experiment, out: str | Path, *, workers: int = 1, backend: str = "local",
                   address: str | None = None, only: Iterable[str] | None = None,
                   on_result: Callable[[sweep.SweepResult], None] | None = None,
                   say: Callable[[str], None] = print) -> list[sweep.SweepResult]:
    """Train (or resume) every selected run: first the plain runs of the scenarios, then the
    comparisons' transfer runs stage by stage (each needs the previous stage's run of its seed)."""
    out = Path(out).resolve()  # absolute: Ray runs tasks in other working directories
    stems, comparisons = selected(experiment, only)

    def run(jobs: list[sweep.SweepJob]) -> list[sweep.SweepResult]:
        jobs = [dataclasses.replace(job, index=i) for i, job in enumerate(jobs)]
        if not jobs:
            return []
        if backend == "ray":
            return sweep.run_ray(jobs, address, on_result=on_result)
        if workers == 1:
            return sweep.run_serial(jobs, on_result=on_result)
        return sweep.run_local(jobs, workers, on_result=on_result)

    jobs = []
    for scenario in experiment.scenarios:
        if scenario.stem in stems:
            jobs += sweep.plan(trained_world(scenario, out), experiment.seeds_of(scenario),
                               [(scenario.stem, scenario.overrides)],
                               scenario_root(out), autopilot=experiment.autopilot)
    say(f"experiment {experiment.name}: {len(jobs)} scenario runs under {out / 'runs'}")
    results = run(jobs)
    for stage in range(1, max((len(c.stems) for c in comparisons), default=0)):
        jobs = []
        for comparison in comparisons:
            if stage < len(comparison.stems):
                jobs += _transfer_jobs(experiment, out, comparison, stage, say)
        say(f"experiment {experiment.name}: {len(jobs)} transfer runs (stage {stage + 1})")
        results += run(jobs)
    jobs = [job for comparison in comparisons if comparison.control for job in _control_jobs(experiment, out, comparison)]
    if jobs:
        say(f"experiment {experiment.name}: {len(jobs)} control runs")
        results += run(jobs)
    sweep.write_summary(out / "runs", results)
    _log_invocation(out, workers=workers, backend=backend, only=only, results=results)
    return results


def _log_invocation(out: Path, *, workers: int, backend: str, only: Iterable[str] | None,
                    results: list[sweep.SweepResult]) -> None:
    """One line per training invocation (the wall times depend on how many runs shared the CPU)."""
    import json
    import time

    from sitl_bridge.rl.common.atomic import append_durably

    record = {"finished": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "workers": workers,
              "backend": backend, "only": sorted(only) if only is not None else None,
              "trained": sum(r.status == "done" for r in results),
              "skipped": sum(r.status == "skipped" for r in results),
              "failed": sum(r.status == "failed" for r in results)}
    append_durably(out / "runs" / INVOCATIONS_FILE, (json.dumps(record) + "\n").encode())


def invocations(out: str | Path) -> list[dict[str, Any]]:
    """The training invocations logged under `out`, oldest first."""
    import json

    path = Path(out) / "runs" / INVOCATIONS_FILE
    rows = []
    for line in (path.read_text().splitlines() if path.is_file() else []):
        try:
            rows.append(json.loads(line))
        except ValueError:
            continue
    return rows


def target_overrides(experiment: Experiment, comparison: ComparisonSpec) -> dict[str, Any]:
    """The `train:` overrides of the comparison's transfer runs (the scenario's, then the stage's)."""
    return {**experiment.scenario(comparison.target).overrides, **comparison.stage_overrides[-1]}


def control_epsilon(experiment: Experiment, comparison: ComparisonSpec) -> float:
    """Where the transfer runs start exploring: the control runs start there too."""
    world = experiment.scenario(comparison.target).world
    return load_train_config(world, target_overrides(experiment, comparison)).transfer_epsilon_max


def _control_jobs(experiment: Experiment, out: Path, comparison: ComparisonSpec) -> list[sweep.SweepJob]:
    scenario = experiment.scenario(comparison.target)
    overrides = {**target_overrides(experiment, comparison), "epsilon_max": control_epsilon(experiment, comparison)}
    jobs = sweep.plan(scenario.world, experiment.seeds, [(scenario.stem, overrides)],
                      control_root(out, comparison.name), autopilot=experiment.autopilot)
    return [dataclasses.replace(job, point=f"{comparison.name}/control/{scenario.stem}") for job in jobs]


def _transfer_jobs(experiment: Experiment, out: Path, comparison: ComparisonSpec, stage: int,
                   say: Callable[[str], None]) -> list[sweep.SweepJob]:
    from sitl_bridge.rl.learner.checkpoint import best_checkpoint

    scenario = experiment.scenario(comparison.stems[stage])
    overrides = {**scenario.overrides, **comparison.stage_overrides[stage]}
    jobs = []
    for seed in experiment.seeds:
        earlier = stage_folder(out, comparison, stage - 1, seed)
        source = run_of(earlier)
        if source is None or not finished(earlier):
            say(f"  {comparison.name} seed {seed}: not started, its earlier run {earlier} has not finished")
            continue
        (job,) = sweep.plan(scenario.world, [seed], [(scenario.stem, overrides)],
                            transfer_root(out, comparison.name), autopilot=experiment.autopilot)
        # the point names the comparison (the sweep's summary rows), the folder stays stage_folder's
        jobs.append(dataclasses.replace(job, point=f"{comparison.name}/{scenario.stem}",
                                        init_from=str(best_checkpoint(source))))
    return jobs
