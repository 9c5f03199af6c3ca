"""Incremental complexity: train scenarios in order, each starting from the previous one's network,
and re-test every new policy in the earlier (simpler) scenarios.

A curriculum file (`worlds/curricula/er_te.yaml`)::

    curriculum:
      name: er_te
      eval_episodes: 50            # greedy episodes per evaluation
      stages:
        - world: worlds/random_goal.yaml
        - world: worlds/two_drones_empty.yaml
          train: {transfer_epsilon_max: 0.5}   # overrides of that world's train: section

World paths are relative to the current directory, or else to the curriculum file. The stages run
in `OUT/{name}__{seed}/`; `curriculum.json` there records every stage's run directory, so running
the same command again resumes where it stopped (finished stages are not re-trained).
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from sitl_bridge.errors import ConfigError, Node, load_yaml
from sitl_bridge.rl.common.atomic import atomic_write_json
from sitl_bridge.rl.common.drones_env import scenario_env_factory
from sitl_bridge.rl.evaluation.evaluate import evaluate_checkpoint
from sitl_bridge.rl.learner.config import load_train_config, parse_train_node
from sitl_bridge.rl.training.init_from import ShapeMismatch
from sitl_bridge.rl.training.run_dir import RunSpec
from sitl_bridge.rl.training.runs import resume_run, start_run

log = logging.getLogger(__name__)
STATE_FILE = "curriculum.json"


@dataclass(frozen=True)
class Stage:
    world: str
    overrides: dict[str, Any]


@dataclass(frozen=True)
class Curriculum:
    name: str
    stages: tuple[Stage, ...]
    eval_episodes: int
    source: str


def world_path(node: Node, base: Path) -> str:
    """The scenario file a config names, relative to the current directory or else to `base`
    (the folder of the file naming it)."""
    text = node.string()
    for candidate in (Path(text), base / text):
        if candidate.is_file():
            return os.path.normpath(candidate)
    raise node.error("an existing scenario file (relative to the current directory or to this file)")


def load_curriculum(path: str | Path) -> Curriculum:
    """Parse a curriculum file; errors are one-line ConfigErrors naming the key."""
    root = load_yaml(path)
    root.reject_unknown({"curriculum"})
    node = root.get("curriculum")
    node.reject_unknown({"name", "stages", "eval_episodes"})
    stages: list[Stage] = []
    for item in node.get("stages").list(min_len=1):
        item.reject_unknown({"world", "train"})
        world = world_path(item.get("world"), Path(path).parent)
        train = item.get("train", None)
        # Validate the overrides against the world's own train: section now, not after hours.
        parse_train_node(train, load_train_config(world))
        stages.append(Stage(world, dict(train.value or {})))
    check_transfers([stage.world for stage in stages], source=str(path))
    return Curriculum(
        name=node.get("name", Path(path).stem).string(),
        stages=tuple(stages),
        eval_episodes=node.get("eval_episodes", 50).integer(minimum=0),
        source=str(path),
    )


def check_transfers(worlds: list[str], source: str) -> None:
    """Fail before any training when a stage's network cannot feed the next (input sizes differ)."""
    from sitl_bridge.envs.scenario import load_scenario

    sizes = [load_scenario(world).task.observation_size for world in worlds]
    for i in range(len(worlds) - 1):
        (a, size_a), (b, size_b) = (worlds[i], sizes[i]), (worlds[i + 1], sizes[i + 1])
        if size_a != size_b:
            raise ShapeMismatch(
                f"{source}: cannot transfer {a} ({size_a} inputs) -> {b} ({size_b} inputs); pad the "
                "smaller observation with a `dummy: N` feature so both have the same size")


@dataclass
class StageReport:
    stage: int
    world: str
    run_dir: str
    episodes: int = 0
    evaluations: list[dict] = field(default_factory=list)
    """Greedy evaluation of this stage's policy in its own and every earlier scenario."""


def run_curriculum(curriculum: Curriculum, out: str | Path, *, seed: int = 0, autopilot: str = "direct",
                   progress: bool = True, say: Callable[[str], None] = print) -> list[StageReport]:
    """Run (or resume) every stage in order; returns one report per stage."""
    folder = Path(out) / f"{curriculum.name}__{seed}"
    folder.mkdir(parents=True, exist_ok=True)
    state_path = folder / STATE_FILE
    state = json.loads(state_path.read_text()) if state_path.exists() else {"stages": []}
    reports = [StageReport(**r) for r in state["stages"]]
    previous: str | None = reports[-1].run_dir if reports else None
    for index, stage in enumerate(curriculum.stages):
        done = index < len(reports) and reports[index].evaluations
        if done:
            previous = reports[index].run_dir
            continue
        config = load_train_config(stage.world, stage.overrides)
        if index < len(reports):  # started before: resume it
            trainer = resume_run(reports[index].run_dir, progress=progress)
        else:
            spec = RunSpec(world=stage.world, autopilot=autopilot, seed=seed, init_from=previous)
            trainer = start_run(folder, spec, config, scenario_env_factory(stage.world, autopilot),
                                    progress=progress)
            reports.append(StageReport(index, stage.world, str(trainer.run_dir)))
            _save(state_path, curriculum, reports)
        say(f"stage {index + 1}/{len(curriculum.stages)}: {stage.world} -> {trainer.run_dir}"
            + (f" (from {previous})" if previous else ""))
        with trainer:
            result = trainer.train()
        report = reports[index]
        report.episodes = result.episodes
        # The thesis's check: does the new rule still work in the simpler scenarios?
        for earlier in curriculum.stages[: index + 1]:
            report.evaluations.append(_evaluate(report.run_dir, earlier.world, curriculum.eval_episodes,
                                                autopilot, seed, say))
        _save(state_path, curriculum, reports)
        previous = report.run_dir
    return reports


def _evaluate(run_dir: str, world: str, episodes: int, autopilot: str, seed: int,
              say: Callable[[str], None]) -> dict:
    try:
        result, _ = evaluate_checkpoint(run_dir, world, episodes=episodes, autopilot=autopilot, seed=seed)
    except (ValueError, ConfigError) as exc:  # e.g. the earlier scenario has another input size
        say(f"  {world}: not evaluated ({exc})")
        return {"world": world, "error": str(exc)}
    say("  " + result.summary())
    return result.to_dict()


def _save(path: Path, curriculum: Curriculum, reports: list[StageReport]) -> None:
    atomic_write_json(path, {"curriculum": curriculum.source, "name": curriculum.name,
                             "stages": [asdict(r) for r in reports]})
