"""A run keeps its best greedy checkpoint as its result (OR must not lose what it
learned when later training collapses): `best.safetensors` + `best.json`, and run directories
resolve to it unless the newest is asked for."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from test_rl_helpers import corridor_factory, tiny_config

from sitl_bridge.rl.learner.checkpoint import BEST_CHECKPOINT, load_checkpoint, resolve_checkpoint
from sitl_bridge.rl.training.run_dir import BEST_FILE, EVALS_FILE, RunSpec
from sitl_bridge.rl.training.run_evaluation import selection_score
from sitl_bridge.rl.training.trainer import Trainer


def test_best_checkpoint_is_the_best_evaluation_and_the_runs_result(tmp_path: Path) -> None:
    config = tiny_config(episodes=13, eval_every=2, eval_episodes=3, stop_on_success=0.0)
    with Trainer.start(tmp_path, RunSpec(world="corridor.yaml"), config, corridor_factory(),
                       progress=False) as trainer:
        trainer.train()
        run_dir = trainer.run_dir
    evals = [json.loads(line) for line in (run_dir / EVALS_FILE).read_text().splitlines()]
    assert len(evals) == 6
    best = json.loads((run_dir / BEST_FILE).read_text())
    top = max(evals, key=lambda e: (e["success_rate"], e["mean_reward"]))
    # the first evaluation with the top score (a tie does not replace the earlier one)
    assert best["after_episodes"] == top["after_episodes"]
    assert best["success_rate"] == top["success_rate"]
    _, state = load_checkpoint(run_dir / BEST_CHECKPOINT)
    assert state["episode"] == best["after_episodes"]

    assert resolve_checkpoint(run_dir)[0] == run_dir / BEST_CHECKPOINT
    newest, _, newest_state = resolve_checkpoint(run_dir, latest=True)
    assert newest.parent.name == "checkpoints" and newest_state["episode"] == 13


def test_a_damaged_best_checkpoint_falls_back_to_the_newest(tmp_path: Path) -> None:
    config = tiny_config(episodes=4, eval_every=2, eval_episodes=2, stop_on_success=0.0)
    with Trainer.start(tmp_path, RunSpec(world="corridor.yaml"), config, corridor_factory(),
                       progress=False) as trainer:
        trainer.train()
        run_dir = trainer.run_dir
    best = run_dir / BEST_CHECKPOINT
    best.write_bytes(best.read_bytes()[:-10])
    path, _, state = resolve_checkpoint(run_dir)
    assert path.parent.name == "checkpoints" and state["episode"] == 4


def test_a_stop_is_confirmed_on_more_evaluation_episodes(tmp_path: Path) -> None:
    config = tiny_config(episodes=2, eval_every=0, eval_episodes=2, stop_on_success=0.9,
                         stop_confirm_episodes=3)
    with Trainer.start(tmp_path, RunSpec(world="corridor.yaml"), config, corridor_factory(),
                       progress=False) as trainer:
        trainer.train()
        # a network that always hovers (7) never reaches the goal: the short evaluation stands
        trainer.agent.q_values = lambda obs: np.eye(8)[7]
        assert trainer.evaluate().episodes == 2
        # one that always flies to the goal (6) reaches the stop threshold: confirmed on 2 + 3
        trainer.agent.q_values = lambda obs: np.eye(8)[6]
        result = trainer.evaluate()
        assert result.episodes == 5 and result.success_rate == 1.0
        run_dir = trainer.run_dir
    evals = [json.loads(line) for line in (run_dir / EVALS_FILE).read_text().splitlines()]
    assert [e["episodes"] for e in evals[-2:]] == [2, 5]
    assert json.loads((run_dir / BEST_FILE).read_text())["episodes"] == 5


def test_an_evaluation_extended_from_a_shorter_one_equals_one_flown_whole() -> None:
    from sitl_bridge.rl.common.drones_env import DronesEnv
    from sitl_bridge.rl.evaluation.evaluate import evaluate_on

    env = DronesEnv(corridor_factory()(0))
    try:
        # a policy whose outcome depends on the start, so the episodes differ
        def policy(obs: np.ndarray) -> int:
            return 6 if obs[0] < 0.5 else 7

        whole, whole_traces = evaluate_on(env, policy, world="corridor", episodes=5, seed=3)
        _, short = evaluate_on(env, policy, world="corridor", episodes=2, seed=3)
        extended, traces = evaluate_on(env, policy, world="corridor", episodes=5, seed=3, flown=short)
    finally:
        env.close()
    assert extended == whole
    assert [(t.episode, t.seed, t.actions, t.outcome) for t in traces] == \
        [(t.episode, t.seed, t.actions, t.outcome) for t in whole_traces]


def test_the_best_checkpoint_ranks_evaluations_of_different_lengths_by_their_lower_bound() -> None:
    # one length: the order of the success rates (then of the rewards), as before
    assert selection_score(18 / 20, 20, 0.0) < selection_score(19 / 20, 20, -50.0)
    assert selection_score(19 / 20, 20, 1.0) < selection_score(19 / 20, 20, 2.0)
    # a confirmed 87 of 100 outranks 35 of 40 (87.5 %), and 100 of 100 outranks 20 of 20
    assert selection_score(35 / 40, 40, 9.0) < selection_score(0.87, 100, 0.0)
    assert selection_score(1.0, 20, 9.0) < selection_score(1.0, 100, 0.0)
