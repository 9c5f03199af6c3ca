"""`train.num_envs` > 1: the trainer flies waves of episodes on `make_vec_env`'s copies (real
simulator, `direct`, tiny budgets). Each episode keeps its own reset seed; a run stopped or
SIGKILLed mid-way and resumed ends with the same episode log and checkpoint as an uninterrupted
one; multi-drone scenarios are refused in one line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from test_rl_cli import (
    TINY,
    TWO_DRONES,
    cli,
    only_run,
    short_scenario,
    sigkill_training_midway,
)
from test_rl_helpers import corridor_factory, tiny_config

from sitl_bridge.rl.common.episode_log import read_records
from sitl_bridge.rl.evaluation.rollout import episode_seed
from sitl_bridge.rl.learner.checkpoint import list_checkpoints, load_checkpoint
from sitl_bridge.rl.learner.config import TrainConfig
from sitl_bridge.rl.learner.dqn import DQNAgent, NetworkShape
from sitl_bridge.rl.training.run_dir import RunSpec
from sitl_bridge.rl.training.trainer import Trainer, read_run_records

EPISODES = 5  # waves of 2: episodes 0-1, 2-3, then 4 alone
ARGS = ["--episodes", str(EPISODES), "--num-envs", "2", "--seed", "4", *TINY[:-1], "--eval-episodes", "0",
        "--no-progress"]


def same(record: dict) -> tuple:
    """Everything of a record that must repeat exactly (wall time excluded)."""
    return (record["episode"], record["actions"], record["reward"], record["outcome"], record["env_seed"],
            record["epsilon"], record["mean_loss"], record["global_step"], record["steps"])


def checkpoint_of(run: Path) -> tuple[dict[str, torch.Tensor], dict]:
    """The newest checkpoint's tensors and state, less what records wall time (the log's bytes)."""
    tensors, state = load_checkpoint(list_checkpoints(run / "checkpoints")[0])
    for key in ("log_bytes", "log_sha256"):
        state.pop(key)
    return tensors, state


def assert_same_checkpoint(a: Path, b: Path) -> None:
    (ta, sa), (tb, sb) = checkpoint_of(a), checkpoint_of(b)
    assert sa == sb
    assert ta.keys() == tb.keys() and all(torch.equal(ta[k], tb[k]) for k in ta)


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> str:
    return short_scenario(tmp_path_factory.mktemp("world"))


@pytest.fixture(scope="module")
def reference(world: str, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("ref")
    assert cli("train", world, *ARGS, "--out", str(out)) == 0
    return only_run(out)


def test_num_envs_2_writes_a_run_dir_of_waves_with_each_episodes_own_seed(reference: Path) -> None:
    records = read_records(reference / "episodes.jsonl")
    assert [r["episode"] for r in records] == list(range(EPISODES))
    assert [r["env_seed"] for r in records] == [episode_seed(4, e) for e in range(EPISODES)]
    assert all(r["outcome"] in ("goal", "crash", "out", "timeout") and len(r["actions"]) == r["steps"] > 0
               for r in records)
    # Episodes of a wave start together (same epsilon); the global step counts every copy's steps.
    assert records[0]["epsilon"] == records[1]["epsilon"] == 1.0 > records[2]["epsilon"]
    assert max(r["global_step"] for r in records) == sum(r["steps"] for r in records)
    assert max(records[0]["global_step"], records[1]["global_step"]) == records[0]["steps"] + records[1]["steps"]
    # One checkpoint per wave, naming the episodes done.
    names = sorted(p.name for p in (reference / "checkpoints").glob("ckpt_*.safetensors"))
    assert names == ["ckpt_0000002.safetensors", "ckpt_0000004.safetensors", "ckpt_0000005.safetensors"]
    _, state = checkpoint_of(reference)
    assert state["config"]["num_envs"] == 2 and state["global_step"] == sum(r["steps"] for r in records)
    assert (reference / "config.yaml").read_text().count("num_envs: 2") == 1


def test_a_stopped_then_resumed_run_equals_the_uninterrupted_one(world: str, reference: Path,
                                                                 tmp_path: Path) -> None:
    from sitl_bridge.rl.common.drones_env import scenario_env_factory
    from sitl_bridge.rl.learner.config import load_train_config

    config = load_train_config(world, {"episodes": EPISODES, "num_envs": 2, "batch_size": 16, "layers": 2,
                                       "hidden_units": 16, "eval_every": 0, "eval_episodes": 0})
    with Trainer.start(tmp_path, RunSpec(world=world, seed=4), config, scenario_env_factory(world),
                       progress=False) as trainer:
        trainer.train(on_episode=lambda records: False)  # stop after the first wave
        assert trainer.episode == 2
    run = only_run(tmp_path)
    assert cli("train", "--resume", str(run), "--no-progress") == 0
    assert [same(r) for r in read_records(run / "episodes.jsonl")] == \
        [same(r) for r in read_records(reference / "episodes.jsonl")]
    assert_same_checkpoint(run, reference)


def test_a_run_killed_mid_wave_resumes_exactly(world: str, reference: Path, tmp_path: Path) -> None:
    out = tmp_path / "killed"
    # Into the second wave: a random fraction of the time the first one took.
    sigkill_training_midway(["train", world, *ARGS], out, lambda records: np.random.default_rng().uniform(0.2, 0.8)
                            * max(r["wall_time_s"] for r in records))
    run = only_run(out)
    logged = read_records(run / "episodes.jsonl")
    assert len(logged) % 2 == 0 and len(logged) < EPISODES  # whole waves only: the one in flight is lost
    assert cli("train", "--resume", str(run), "--no-progress") == 0
    assert [same(r) for r in read_records(run / "episodes.jsonl")] == \
        [same(r) for r in read_records(reference / "episodes.jsonl")]
    assert_same_checkpoint(run, reference)


def test_any_env_factory_gives_copies_and_every_option_resumes_exactly(tmp_path: Path) -> None:
    """The corridor (not a scenario file): copies come from its factory; n-step, prioritized
    replay, normalisation, per-episode target updates and several updates each time they are due
    survive a resume inside a run of waves."""
    config = tiny_config(episodes=7, num_envs=3, n_step=3, prioritized_replay=True, normalize_observations=True,
                         target_update_unit="episodes", target_update_period=2, train_every=2, gradient_steps=2)
    spec = RunSpec(world="corridor.yaml", seed=5)
    with Trainer.start(tmp_path / "ref", spec, config, corridor_factory(), progress=False) as ref:
        ref.train()
    with Trainer.start(tmp_path / "cut", spec, config, corridor_factory(), progress=False) as cut:
        cut.train(on_episode=lambda records: False)
        assert [r["episode"] for r in read_run_records(cut.run_dir)] == [0, 1, 2]
    with Trainer.resume(cut.run_dir, corridor_factory(), progress=False) as resumed:
        resumed.train()
    a, b = read_run_records(ref.run_dir), read_run_records(resumed.run_dir)
    assert [r["episode"] for r in a] == list(range(7))
    assert [r["env_seed"] for r in a] == [episode_seed(5, e) for e in range(7)]
    assert [same(r) for r in a] == [same(r) for r in b]
    assert_same_checkpoint(ref.run_dir, resumed.run_dir)
    assert ref.updates > 0 and ref.updates % 2 == 0  # two updates each time they are due


def test_act_batch_draws_as_act_does_row_by_row() -> None:
    agent = DQNAgent(NetworkShape(3, 5, 2, 8), TrainConfig(), torch.device("cpu"))
    obs = np.random.default_rng(0).normal(size=(6, 3)).astype(np.float32)
    for epsilon in (0.0, 0.5, 1.0):
        one, batch = np.random.default_rng(1), np.random.default_rng(1)
        expected = [agent.act(row, epsilon, one) for row in obs]
        assert agent.act_batch(obs, epsilon, batch).tolist() == expected
        assert one.random() == batch.random()  # the same draws were consumed


def test_multi_drone_scenarios_with_several_copies_are_one_line_errors(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli("train", TWO_DRONES, "--episodes", "1", "--num-envs", "2", "--out", str(tmp_path), *TINY) == 2
    err = capsys.readouterr().err
    assert "single-drone" in err and "num_envs" in err and err.count("\n") == 1
    assert not list(tmp_path.iterdir())  # no run directory left behind
