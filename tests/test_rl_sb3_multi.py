"""Stable-Baselines3 algorithms on multi-drone scenarios: one policy shared by every drone
(parameter sharing, as the DQN side does), each drone's transitions in the one buffer, the DQN
run directory with per-drone records, evaluation, and kill -9 resumes continuing exactly."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from test_rl_kill_faults import _jsonl, assert_same_run, kill_and_resume
from test_rl_sb3 import PPO_TINY, cli, scenario

pytest.importorskip("stable_baselines3")

CONTINUOUS = "two_drones_empty_relative_continuous.yaml"
DISCRETE = "two_drones_empty_relative.yaml"
SAC_TWO = {"buffer_size": 1000, "learning_starts": 20, "batch_size": 16, "train_freq": 4, "gradient_steps": 2,
           "policy_kwargs": {"net_arch": [16, 16]}}


def _replay_rows(run: Path) -> int:
    total = 0
    for shard in (run / "replay").glob("*.npz"):
        with np.load(shard) as arrays:
            total += len(arrays["rewards"])
    return total


@pytest.mark.parametrize(("world_name", "algorithm", "arguments", "task"), [
    (CONTINUOUS, "ppo", PPO_TINY, {"max_time_s": 1.5}),
    (CONTINUOUS, "sac", SAC_TWO, {"max_time_s": 1.5}),
    (DISCRETE, "ppo", PPO_TINY, {"max_steps": 6}),
], ids=["ppo-continuous", "sac-continuous", "ppo-discrete"])
def test_two_drones_train_one_shared_policy_then_evaluate(tmp_path: Path, capsys: pytest.CaptureFixture,
                                                          world_name: str, algorithm: str, arguments: dict,
                                                          task: dict) -> None:
    from sitl_bridge.rl.learner.policy import policy_from_checkpoint

    world = scenario(tmp_path, world_name, {"algorithm": algorithm, algorithm: arguments, "experiment": "tiny"},
                     **task)
    cli(capsys, "train", str(world), "--seed", "1", "--episodes", "4", "--eval-every", "2", "--eval-episodes", "2",
        "--out", str(tmp_path / "runs"), "--no-progress")
    (run,) = (tmp_path / "runs").iterdir()
    records = _jsonl(run / "episodes.jsonl")
    assert [(r["episode"], r["drone"]) for r in records] == [(e, d) for e in range(4) for d in (0, 1)]
    assert all(r["steps"] == len(r["actions"]) > 0 for r in records)
    assert any(r["mean_loss"] is not None for r in records)  # the shared policy was trained
    if algorithm == "sac":  # one replay row per drone-step: both drones' transitions
        assert _replay_rows(run) == sum(r["steps"] for r in records)
    # env steps count once for both drones acting at once, as DQN counts them
    assert records[-1]["global_step"] == sum(max(r["steps"] for r in records if r["episode"] == e) for e in range(4))
    evals = _jsonl(run / "evals.jsonl")
    assert [e["after_episodes"] for e in evals] == [2, 4]
    assert all(e["drone_episodes"] == 4 for e in evals)  # 2 episodes x 2 drones
    assert (run / "best.safetensors").is_file()
    policy = policy_from_checkpoint(run)
    assert (policy.algorithm, policy.continuous) == (algorithm, world_name == CONTINUOUS)
    evaluated = json.loads(cli(capsys, "eval", str(run), "--episodes", "2", "--json", stdout_only=True))
    assert (evaluated["episodes"], evaluated["drone_episodes"]) == (2, 4)



def test_ppo_learns_from_each_drones_stream_as_sb3_would_from_that_drone_alone() -> None:
    """Drones end their episodes at different steps (crash, time limit) and rollouts fill
    mid-episode: the advantages PPO trains on are, stream by stream, SB3's own GAE of that drone
    alone (a one-env RolloutBuffer)."""
    from stable_baselines3.common.buffers import RolloutBuffer

    from sitl_bridge.rl.learner.sb3_learner import SB3Learner

    space = gym.spaces.Box(-1, 1, (2,), np.float32)
    learner = SB3Learner("ppo", 3, space, {"n_steps": 6, "batch_size": 3, "policy_kwargs": {"net_arch": [8]}},
                         seed=0, num_drones=2)
    model = learner.model
    trained: list[np.ndarray] = []
    model.train = lambda: trained.append(model.rollout_buffer.advantages.reshape(-1).copy())
    rng = np.random.default_rng(3)

    def value(obs: np.ndarray) -> float:
        with torch.no_grad():
            return float(model.policy.predict_values(torch.as_tensor(obs.reshape(1, -1)))[0])

    def alone(rows: list[tuple], last_obs: np.ndarray | None) -> np.ndarray:
        """SB3's GAE of one drone's rows (obs, reward, episode start) in a one-env buffer."""
        buffer = RolloutBuffer(len(rows), model.observation_space, space, gamma=model.gamma,
                               gae_lambda=model.gae_lambda)
        for o, reward, start in rows:
            buffer.add(o.reshape(1, -1), np.zeros((1, 2)), np.array([reward]), np.array([start]),
                       torch.tensor([[value(o)]]), torch.zeros(1))
        flying = last_obs is not None
        buffer.compute_returns_and_advantage(torch.tensor([value(last_obs) if flying else 0.0]),
                                             np.array([not flying]))
        return buffer.advantages.reshape(-1)

    expected: list[np.ndarray] = []
    rows: dict[int, list[tuple]] = {0: [], 1: []}
    # (step, how) each drone's episode ends at: the first rollout fills in episode 2 with both
    # drones flying; the second starts mid-episode for both and fills as drone 1 hits the limit
    scripts = [{0: (4, "limit"), 1: (2, "crash")}, {0: (5, "crash"), 1: (8, "limit")}]
    for ends in scripts:
        obs = {i: rng.normal(size=3).astype(np.float32) for i in (0, 1)}
        learner.start_episode(obs)
        live, step = [0, 1], 0
        while live:
            learner.act(live)
            step += 1
            nxt = {i: rng.normal(size=3).astype(np.float32) for i in live}
            rewards = {i: float(rng.normal()) for i in live}
            term = {i: ends[i] == (step, "crash") for i in live}
            trunc = {i: ends[i] == (step, "limit") for i in live}
            for i in live:
                bootstrap = model.gamma * value(nxt[i]) if trunc[i] else 0.0  # a time limit, as SB3 does
                rows[i].append((obs[i], np.float32(rewards[i] + bootstrap), step == 1))
            before = len(trained)
            learner.step(live, rewards, nxt, term, trunc)
            obs.update(nxt)
            live = [i for i in live if not (term[i] or trunc[i])]
            if len(trained) > before:
                expected.append(np.concatenate([alone(rows[i], obs[i] if i in live else None) for i in (0, 1)]))
                rows = {0: [], 1: []}
        learner.end_episode()
    assert len(trained) == 2
    assert [len(a) for a in trained] == [6 + 4, 3 + 6]
    for mine, theirs in zip(trained, expected, strict=True):
        np.testing.assert_allclose(mine, theirs, rtol=1e-5, atol=1e-5)
    assert learner.rollout_pos == [0, 0]  # the rollout starts over after each update


def _killed_and_resumed(tmp_path: Path, world: Path, kill_after: int, episodes: int) -> tuple[Path, Path]:
    return kill_and_resume(tmp_path, [str(world), "--seed", "5", "--episodes", str(episodes), "--eval-every", "2",
                                      "--eval-episodes", "1"], lambda beat: beat["episode"] >= kill_after)


@pytest.mark.slow  # about 40 s: two runs at once, one killed and resumed
def test_sac_on_two_drones_killed_9_resumes_exactly_with_the_same_replay(tmp_path: Path) -> None:
    sac = {**SAC_TWO, "buffer_size": 70}  # both drones' rows wrap the ring: old shards are pruned
    world = scenario(tmp_path, CONTINUOUS, {"algorithm": "sac", "sac": sac}, max_time_s=1.5)
    run_dir, reference = _killed_and_resumed(tmp_path, world, 3, 6)
    assert_same_run(run_dir, reference)  # same episodes of both drones, evaluations, weights, optimizers
    shards = sorted(p.name for p in (run_dir / "replay").glob("*.npz"))
    assert shards == sorted(p.name for p in (reference / "replay").glob("*.npz"))
    assert not shards[0].startswith("r000000000000_")
    for name in shards:
        with np.load(run_dir / "replay" / name) as mine, np.load(reference / "replay" / name) as theirs:
            assert all(np.array_equal(mine[k], theirs[k]) for k in theirs.files), name
    records = _jsonl(run_dir / "episodes.jsonl")
    last_shard_end = int(shards[-1].split("_")[1].removesuffix(".npz"))
    assert last_shard_end == sum(r["steps"] for r in records)  # every drone-step is a replay row


@pytest.mark.slow  # about 40 s: two runs at once, one killed and resumed
def test_ppo_on_two_drones_killed_9_resumes_exactly_with_the_same_rollout(tmp_path: Path) -> None:
    ppo = {**PPO_TINY, "n_steps": 8, "batch_size": 4}
    world = scenario(tmp_path, DISCRETE, {"algorithm": "ppo", "ppo": ppo}, max_steps=6)
    run_dir, reference = _killed_and_resumed(tmp_path, world, 3, 6)
    records = _jsonl(run_dir / "episodes.jsonl")
    assert [(r["episode"], r["drone"]) for r in records] == [(e, d) for e in range(6) for d in (0, 1)]
    assert sum(r["mean_loss"] is not None for r in records) >= 2 * 2  # PPO updated, before and after the kill
    assert_same_run(run_dir, reference)  # same actions, evaluations, weights, optimizer, partial rollout
