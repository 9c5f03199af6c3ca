"""Fly the greedy policies of several runs (seeds) of one scenario and analyse their behaviour:
action summary, manoeuvre classification per seed, candidate rules (words and rules YAML) and
the thesis's rules 0-5 checked. What `sitl-bridge rules RUN_DIR...` prints.

The observations each drone saw before each step are kept, so that candidate rules can state
their conditions over the scenario's own observation features.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sitl_bridge.envs.scenario import load_scenario
from sitl_bridge.rl.analysis.behaviour import BehaviourAnalysis, RunBehaviour, classify, openings
from sitl_bridge.rl.analysis.behaviour_summary import BehaviourSummary, summarize_behaviour
from sitl_bridge.rl.analysis.candidate_rules import (
    CandidateRule,
    ThesisCheck,
    candidate_rules,
    fidelity,
    rules_document,
    scenario_facts,
    thesis_checks,
)
from sitl_bridge.rl.common.drones_env import DronesEnv, StepResult, scenario_env_factory
from sitl_bridge.rl.evaluation.evaluate import evaluate_on
from sitl_bridge.rl.evaluation.rollout import Trace
from sitl_bridge.rl.learner.policy import policy_from_checkpoint, require_discrete
from sitl_bridge.rl.training.run_dir import read_run_files, run_dir_of, run_scenario


class RecordingEnv(DronesEnv):
    """A `DronesEnv` that keeps every drone's observation before each of its steps:
    `observations[(episode, drone)]` (episodes counted from 0 by resets)."""

    def __init__(self, env: Any) -> None:
        super().__init__(env)
        self.episode = -1
        self._rows: dict[tuple[int, int], list[np.ndarray]] = defaultdict(list)
        self._last: dict[int, np.ndarray] = {}

    def reset(self, seed: int) -> tuple[dict[int, np.ndarray], dict[int, dict[str, Any]]]:
        obs, infos = super().reset(seed)
        self.episode += 1
        self._last = {i: o.copy() for i, o in obs.items()}
        return obs, infos

    def step(self, actions: dict[int, int]) -> StepResult:
        for i in actions:
            self._rows[(self.episode, i)].append(self._last[i])
        result = super().step(actions)
        self._last.update({i: o.copy() for i, o in result.obs.items()})
        return result

    @property
    def observations(self) -> dict[tuple[int, int], np.ndarray]:
        return {key: np.array(rows) for key, rows in self._rows.items()}


def run_label(path: str | Path) -> str:
    """A run's training seed (from run.json), or the file's name outside a run directory."""
    run_dir = run_dir_of(path)
    return str(read_run_files(run_dir)[0].seed) if run_dir is not None else Path(path).name


def scenario_file_name(path: str | Path) -> str:
    """The scenario file name a run trained in (its run.json `world`), or `path`'s own name."""
    run_dir = run_dir_of(path)
    return Path(read_run_files(run_dir)[0].world).name if run_dir is not None else Path(path).name


def fly_recorded(checkpoint: str | Path, world: str | Path, *, episodes: int, seed: int = 0,
                 autopilot: str = "direct", progress: bool = False, desc: str = "rules",
                 ) -> tuple[list[Trace], dict[tuple[int, int], np.ndarray]]:
    """Greedy rollouts of a checkpoint on the evaluation seeds (as `eval`), with observations."""
    policy = require_discrete(policy_from_checkpoint(checkpoint), "rule extraction")
    env = RecordingEnv(scenario_env_factory(world, autopilot)(seed))
    try:
        _, traces = evaluate_on(env, policy, world=str(world), episodes=episodes, seed=seed,
                                progress=progress, desc=desc)
    finally:
        env.close()
    return traces, env.observations


@dataclass
class RulesReport:
    """Everything `sitl-bridge rules` reports for a set of runs of one scenario."""

    summary: BehaviourSummary
    analysis: BehaviourAnalysis
    rules: list[CandidateRule]
    checks: list[ThesisCheck]
    document: dict
    """The rules YAML (the format `eval --rules` flies)."""
    fidelity: float | None = None
    """Share of the recorded steps at which the rules YAML picks the network's action."""
    steps: int = 0

    def to_dict(self) -> dict:
        return {**self.summary.to_dict(), "behaviour": self.analysis.to_dict(),
                "candidate_rules": [r.to_dict() for r in self.rules],
                "thesis_rules": [c.to_dict() for c in self.checks], "rules_yaml": self.document,
                "rules_fidelity": self.fidelity, "recorded_steps": self.steps}

    def report(self) -> str:
        lines = [self.summary.report(), self.analysis.report(), "candidate rules (* in the rules YAML):"]
        lines += [f"  {'*' if r.in_yaml else ' '} {r.plain()}"
                  + (f"; agrees with the network in {r.agreement:.0%} of the steps it decides"
                     if r.agreement is not None else "") for r in self.rules]
        if not self.rules:
            lines.append("    none: no episode in which every drone reached its goal")
        if self.fidelity is not None:
            lines.append(f"  the rules YAML picks the network's action at {self.fidelity:.0%} of "
                         f"{self.steps} recorded steps")
        lines.append("thesis rules:")
        lines += [f"  {c.line()}" for c in self.checks]
        return "\n".join(lines)


def analyse_runs(paths: list[str | Path], world: str | Path | None = None, *, episodes: int, seed: int = 0,
                 autopilot: str = "direct", progress: bool = False, top: int = 5) -> RulesReport:
    """Fly every run's greedy policy (in `world`, default each run's own scenario) on the same
    evaluation episodes and analyse them together; the runs are the seeds of one scenario."""
    worlds = [Path(world) if world else run_scenario(path) for path in paths]
    labels = [run_label(path) for path in paths]
    if len(set(labels)) < len(labels):  # two runs with one seed: tell them apart by position
        labels = [f"{label}#{k}" for k, label in enumerate(labels)]
    scenario = load_scenario(worlds[0])
    runs, observations, pooled = [], {}, []
    for path, scenario_path, label in zip(paths, worlds, labels, strict=True):
        traces, recorded = fly_recorded(path, scenario_path, episodes=episodes, seed=seed, autopilot=autopilot,
                                        progress=progress, desc=f"seed {label}")
        pooled += traces
        runs.append(RunBehaviour(label, classify(traces, run=label, priority_rule=scenario.task.priority,
                                                 shared_openings=openings(scenario.world.obstacles))))
        observations.update({(label, e, d): rows for (e, d), rows in recorded.items()})
    file = scenario_file_name(world or paths[0])
    analysis = BehaviourAnalysis(Path(file).stem, runs)
    facts = scenario_facts(scenario, file)
    rules = candidate_rules(analysis, facts, observations)
    summary = summarize_behaviour(str(worlds[0]), episodes * len(paths), pooled, top=top,
                                  frame=scenario.task.action.frame, swap_drones=scenario.task.action.swap_drones)
    document = rules_document(rules, analysis, facts)
    return RulesReport(summary, analysis, rules, thesis_checks(analysis, facts), document,
                       *fidelity(document, analysis, facts, observations))

