"""Slow learning test: TE with the agent-relative inputs (two_drones_empty_relative.yaml)
learns, within a small budget, a greedy policy that beats every constant-action policy (both
drones reach their goals without colliding). Excluded from CI's default run (`-m 'not slow'`).

Status: this is the target, and it FAILS with the file's current, untuned settings (see the
file's task note); it passes once settings that learn TE are found."""

from __future__ import annotations

from pathlib import Path

import pytest

from sitl_bridge.rl.common.drones_env import DronesEnv, scenario_env_factory
from sitl_bridge.rl.evaluation.evaluate import constant_action_baseline
from sitl_bridge.rl.learner.config import load_train_config
from sitl_bridge.rl.training.run_dir import RunSpec
from sitl_bridge.rl.training.trainer import Trainer

TE = Path(__file__).resolve().parents[1] / "worlds" / "two_drones_empty_relative.yaml"
BUDGET = 300
"""Training episodes (about 10 minutes on the direct backend on an unloaded core)."""


@pytest.mark.slow
def test_te_greedy_policy_beats_every_constant_action(tmp_path: Path) -> None:
    config = load_train_config(TE).replace(episodes=BUDGET, eval_every=50, eval_episodes=10)
    factory = scenario_env_factory(TE)
    with Trainer.start(tmp_path, RunSpec(world=str(TE), seed=0), config, factory, progress=False) as trainer:
        trainer.train()
        result = trainer.evaluate(10)
        baseline = constant_action_baseline(DronesEnv(factory(0)), world=str(TE), episodes=10)
    assert baseline.success_rate < 1.0  # no constant action solves TE (action 6 flies head-on)
    assert result.success_rate >= 0.95 > baseline.success_rate
    assert result.crash_rate == 0.0
