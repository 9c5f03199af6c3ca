"""A run's greedy evaluations: each one flown on the held-out evaluation seeds (confirmed on
`stop_confirm_episodes` more when it reaches `stop_on_success`), journalled in `evals.jsonl`
(`eval.json`: the latest); the checkpoint of the best one copied to `best.safetensors`
(`best.json` says which and how well); the best constant-action policy as the baseline that
"solved" must beat (`baseline.json`, measured once per run)."""

from __future__ import annotations

import contextlib
import json
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from sitl_bridge.rl.common.atomic import append_durably, atomic_write_bytes, atomic_write_json
from sitl_bridge.rl.common.drones_env import DronesEnv
from sitl_bridge.rl.common.stats import wilson_interval
from sitl_bridge.rl.evaluation.evaluate import (
    ConstantBaseline,
    EvalResult,
    constant_action_baseline,
    constant_actions,
    evaluate_on,
)
from sitl_bridge.rl.evaluation.rollout import Trace
from sitl_bridge.rl.learner import checkpoint as ckpt
from sitl_bridge.rl.learner.config import TrainConfig
from sitl_bridge.rl.training import run_dir as rd
from sitl_bridge.rl.training.eval_journal import recorded_evaluation
from sitl_bridge.rl.training.train_plan import baseline_notice


class Progressing(Protocol):
    """Where training stands (a learner's counters)."""

    episode: int
    global_step: int


def selection_score(success_rate: float, drone_episodes: int, mean_reward: float) -> tuple[float, float]:
    """How a greedy evaluation ranks for the best checkpoint: the low end of its success rate's
    Wilson 95 % interval, ties by mean reward. Among evaluations of one length this orders as the
    rate itself; across lengths (`stop_confirm_episodes`) a confirmed 87 of 100 outranks 35 of 40."""
    trials = max(int(drone_episodes), 1)
    return wilson_interval(round(success_rate * trials), trials)[0], mean_reward


class RunEvaluator:
    """Greedy evaluations of a run's current network, its best checkpoint and its baseline."""

    def __init__(self, run_dir: Path, spec: rd.RunSpec, config: TrainConfig, env: DronesEnv,
                 greedy_action: Callable[[np.ndarray], Any], at: Progressing, *, progress: bool,
                 beat: Callable[[str], None], warn: Callable[[str], None]) -> None:
        self.run_dir, self.spec, self.config, self.env = run_dir, spec, config, env
        self.greedy_action, self.at = greedy_action, at
        self.progress, self.beat, self.warn = progress, beat, warn

    def evaluate(self, episodes: int | None = None) -> EvalResult:
        """Greedy evaluation of the current network: written to eval.json, the best checkpoint
        kept, appended to evals.jsonl (last: that line marks it done)."""
        episodes = self.config.eval_episodes if episodes is None else episodes
        start, cpu_start = time.perf_counter(), time.process_time()
        result, traces = self._greedy(episodes)
        confirm = self.config.stop_confirm_episodes
        if confirm and self.config.stop_on_success and result.success_rate >= self.config.stop_on_success:
            # 20 episodes at 95 % is one failure from 90 %: a stop (and the best checkpoint)
            # rests on the longer evaluation, which goes on from the episodes just flown.
            result, _ = self._greedy(episodes + confirm, flown=traces)
        record = {**result.to_dict(), "after_episodes": self.at.episode, "global_step": self.at.global_step,
                  "wall_time_s": time.perf_counter() - start, "cpu_time_s": time.process_time() - cpu_start}
        atomic_write_json(self.run_dir / rd.EVAL_FILE, record)
        self.keep_if_best(result)
        # Last: the journal's line marks the evaluation done (rl/training/eval_journal.py).
        append_durably(self.run_dir / rd.EVALS_FILE, (json.dumps(record) + "\n").encode())
        return result

    def _greedy(self, episodes: int, flown: Sequence[Trace] = ()) -> tuple[EvalResult, list[Trace]]:
        return evaluate_on(self.env, self.greedy_action,
                           world=self.spec.world, episodes=episodes, seed=self.spec.seed,
                           progress=self.progress, desc="greedy evaluation", flown=flown, beat=self.beat)

    def recorded_evaluation(self) -> EvalResult | None:
        """The evaluation of the current state that `evals.jsonl` already holds, if any (a
        resumed session does not fly it again)."""
        return recorded_evaluation(self.run_dir / rd.EVALS_FILE, self.at.episode, self.at.global_step)

    def keep_if_best(self, result: EvalResult) -> None:
        """Copy the checkpoint just evaluated to `best.safetensors` when its greedy success beats
        every earlier evaluation's (ties: the higher mean reward). Later training may forget
        what was learned (the thesis's OR collapsed after solving it); the best stays the
        run's result. Resumes compare against `best.json`."""
        source = ckpt.checkpoint_path(self.run_dir / rd.CHECKPOINTS, self.at.episode)
        if not source.is_file():  # evaluated before the state was checkpointed: nothing to keep
            return
        best_file = self.run_dir / rd.BEST_FILE
        score = selection_score(result.success_rate, result.drone_episodes, result.mean_reward)
        with contextlib.suppress(OSError, ValueError, KeyError, TypeError):
            best = json.loads(best_file.read_text())
            # best.json of an older version may lack drone_episodes: its episodes then
            trials = best.get("drone_episodes", best.get("episodes", 1))
            if score <= selection_score(best["success_rate"], trials, best["mean_reward"]):
                return
        atomic_write_bytes(self.run_dir / ckpt.BEST_CHECKPOINT, source.read_bytes())
        atomic_write_json(best_file, {**result.to_dict(), "after_episodes": self.at.episode,
                                      "global_step": self.at.global_step, "checkpoint": source.name})

    def solved(self, result: EvalResult) -> bool:
        """A greedy evaluation solves the scenario when it reaches `stop_on_success` and beats
        the best constant-action policy on the same episodes (else nothing was learned)."""
        if not self.config.stop_on_success or result.success_rate < self.config.stop_on_success:
            return False
        return result.success_rate > self.constant_baseline().success_rate

    def constant_baseline(self) -> ConstantBaseline:
        """The best constant-action policy's greedy success on the evaluation episodes, measured
        once per run and kept in the run directory (`baseline.json`)."""
        path = self.run_dir / rd.BASELINE_FILE
        if path.exists():
            with contextlib.suppress(ValueError, KeyError, TypeError):
                return ConstantBaseline(**json.loads(path.read_text()))
        print(baseline_notice(len(constant_actions(self.env)), self.config.eval_episodes), file=sys.stderr)
        baseline = constant_action_baseline(self.env, world=self.spec.world, episodes=self.config.eval_episodes,
                                            seed=self.spec.seed, progress=self.progress, beat=self.beat)
        atomic_write_json(path, baseline.to_dict())
        if self.config.stop_on_success and baseline.success_rate >= self.config.stop_on_success:
            self.warn(f"always choosing action {baseline.action} already succeeds in "
                      f"{baseline.success_rate:.0%} of the evaluation episodes: this scenario needs no "
                      "learning, so training runs its whole budget")
        return baseline
