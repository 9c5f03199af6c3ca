"""Runs survive anything: SIGKILL mid-episode then --resume continues exactly (no gap, no
duplicate, same numbers as an uninterrupted run), the replay survives, damaged checkpoints fall back
to the previous one, transfers with the wrong shapes fail clearly."""

from __future__ import annotations

import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from test_rl_helpers import CorridorEnv, corridor_factory, tiny_config, train_corridor

from sitl_bridge.rl.learner.checkpoint import (
    CheckpointError,
    list_checkpoints,
    load_checkpoint,
    save_checkpoint,
)
from sitl_bridge.rl.training.init_from import ShapeMismatch
from sitl_bridge.rl.training.run_dir import RunSpec
from sitl_bridge.rl.training.trainer import Trainer, read_run_records

HELPER = Path(__file__).with_name("test_rl_helpers.py")
EPISODES = 8


def comparable(records: list[dict]) -> list[tuple]:
    """Everything of a record that must repeat exactly (wall time excluded)."""
    return [(r["episode"], r["drone"], tuple(r["actions"]), r["reward"], r["outcome"], r["epsilon"],
             r["mean_loss"], r["global_step"], r["env_seed"]) for r in records]


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An uninterrupted run of EPISODES episodes."""
    return Path(train_corridor(str(tmp_path_factory.mktemp("ref")), None, EPISODES, 0.0))


def start_killable(out: Path, run_dir: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, str(HELPER), str(out), run_dir, str(EPISODES), "0.02"],
                            stdout=subprocess.PIPE, text=True, cwd=HELPER.parent.parent,
                            env={**os.environ, "PYTHONPATH": str(HELPER.parent.parent)})


def wait_for_lines(path: Path, count: int, proc: subprocess.Popen, timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if path.exists() and path.read_text().count("\n") >= count:
            return
        assert proc.poll() is None, "training subprocess ended early"
        time.sleep(0.01)
    raise AssertionError(f"{path} never reached {count} lines")


def test_sigkill_mid_episode_then_resume_continues_exactly(tmp_path: Path, reference: Path) -> None:
    rng = random.Random(7)
    proc = start_killable(tmp_path, "-")
    try:
        run_dir = Path(proc.stdout.readline().strip())
        log = run_dir / "episodes.jsonl"
        # Kill twice at random moments inside an episode (each episode takes ~0.25 s here).
        for lines in (2, 5):
            wait_for_lines(log, lines, proc)
            time.sleep(rng.uniform(0.03, 0.2))
            proc.send_signal(signal.SIGKILL)
            proc.wait(timeout=30)
            assert proc.returncode == -signal.SIGKILL
            proc = start_killable(tmp_path, str(run_dir))
        assert proc.wait(timeout=120) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stdout.close()

    records = read_run_records(run_dir)
    assert [r["episode"] for r in records] == list(range(EPISODES))  # no gap, no duplicate
    assert comparable(records) == comparable(read_run_records(reference))

    # The replay survived: same rows, same count as the uninterrupted run.
    resumed = Trainer.resume(run_dir, corridor_factory(), progress=False)
    expected = Trainer.resume(reference, corridor_factory(), progress=False)
    with resumed, expected:
        assert resumed.replay.total_added == sum(r["steps"] for r in records)
        assert len(resumed.replay) == len(expected.replay) == min(resumed.replay.total_added, 40)
        assert resumed.replay.rows.tobytes() == expected.replay.rows.tobytes()
        for a, b in zip(resumed.agent.online.parameters(), expected.agent.online.parameters(), strict=True):
            assert torch.equal(a, b)


@pytest.mark.parametrize("damage", ["truncate", "flip"])
def test_damaged_checkpoint_falls_back_to_previous(tmp_path: Path, reference: Path, damage: str) -> None:
    run_dir = Path(train_corridor(str(tmp_path), None, EPISODES - 1, 0.0))
    newest = list_checkpoints(run_dir / "checkpoints")[0]
    assert newest.name == f"ckpt_{EPISODES - 1:07d}.safetensors"
    data = bytearray(newest.read_bytes())
    if damage == "truncate":
        data = data[: len(data) // 2]
    else:
        data[-5] ^= 0xFF  # inside the last tensor's bytes
    newest.write_bytes(bytes(data))

    warnings: list[str] = []
    trainer = Trainer.resume(run_dir, corridor_factory(), episodes=EPISODES, progress=False, warn=warnings.append)
    with trainer:
        assert trainer.episode == EPISODES - 2
        assert len(warnings) == 1 and newest.name in warnings[0] and "falling back" in warnings[0]
        assert ("truncated" in warnings[0]) if damage == "truncate" else ("checksum" in warnings[0])
        trainer.train()
    assert (run_dir / "checkpoints" / (newest.name + ".corrupt")).exists()
    # The lost episode was re-run: the log is complete and identical to the uninterrupted run.
    assert comparable(read_run_records(run_dir)) == comparable(read_run_records(reference))


def test_checkpoint_round_trip_and_load_errors(tmp_path: Path) -> None:
    path = tmp_path / "ckpt_0000001.safetensors"
    tensors = {"w": torch.arange(6, dtype=torch.float32).reshape(2, 3), "b": torch.tensor([1], dtype=torch.uint8)}
    state = {"episode": 1, "rng": {"numpy": np.random.default_rng(3).bit_generator.state}}
    save_checkpoint(path, tensors, state)
    loaded, loaded_state = load_checkpoint(path)
    assert torch.equal(loaded["w"], tensors["w"]) and loaded_state == state
    assert not list(tmp_path.glob(".*tmp*"))  # no temp file left behind
    path.write_bytes(path.read_bytes()[:10])
    from sitl_bridge.rl.learner.checkpoint import CheckpointCorrupt

    with pytest.raises(CheckpointCorrupt, match="truncated"):
        load_checkpoint(path)


class WideCorridor(CorridorEnv):
    """The corridor with one extra (dummy) observation value: a different input size."""

    def __init__(self) -> None:
        super().__init__()
        import gymnasium as gym

        self.observation_space = gym.spaces.Box(0.0, 1.0, shape=(3,), dtype=np.float32)

    def _obs(self) -> np.ndarray:
        return np.append(super()._obs(), 0.0).astype(np.float32)


def test_init_from_transfers_weights_and_rejects_wrong_shapes(tmp_path: Path) -> None:
    source = Path(train_corridor(str(tmp_path / "a"), None, 2, 0.0))
    spec = RunSpec(world="wide.yaml", init_from=str(source))
    with pytest.raises(ShapeMismatch) as info:
        Trainer.start(tmp_path / "b", spec, tiny_config(), lambda seed: WideCorridor(), progress=False)
    message = str(info.value)
    assert "2 inputs" in message and "8 outputs" in message and "3 inputs" in message

    config = tiny_config(transfer_epsilon_max=0.5, layers=3)  # the source's 2 layers win
    with Trainer.start(tmp_path / "c", RunSpec(world="corridor.yaml", init_from=str(source)), config,
                       corridor_factory(), progress=False) as trainer:
        source_weights, _ = load_checkpoint(list_checkpoints(source / "checkpoints")[0])
        assert torch.equal(trainer.agent.online.net[0].weight, source_weights["online.net.0.weight"])
        assert trainer.config.layers == 2
        assert trainer.epsilon() == 0.5


def test_transfer_replay_starts_from_the_source_runs_transitions_and_keeps_them(tmp_path: Path) -> None:
    source = Path(train_corridor(str(tmp_path / "a"), None, 4, 0.0))
    source_shards = {p.name: p.read_bytes() for p in (source / "replay").glob("seg_*.bin")}
    spec = RunSpec(world="corridor.yaml", seed=1, init_from=str(source))
    with Trainer.start(tmp_path / "b", spec, tiny_config(transfer_replay=True, replay_capacity=1000),
                       corridor_factory(), progress=False) as trainer:
        adopted = len(trainer.replay)
        # every row the source wrote (its shards in order; its own buffer held only the last 40)
        expected = np.frombuffer(b"".join(source_shards[k] for k in sorted(source_shards)),
                                 dtype=trainer.replay.rows.dtype)
        assert adopted == len(expected) > 40
        assert np.array_equal(trainer.replay.rows[:adopted], expected)
        trainer.train()
        run_dir, total = trainer.run_dir, len(trainer.replay)
    assert total > adopted  # the new episodes joined the adopted rows
    # the source run is read, never changed
    assert {p.name: p.read_bytes() for p in (source / "replay").glob("seg_*.bin")} == source_shards
    with Trainer.resume(run_dir, corridor_factory(), progress=False) as resumed:  # own shards hold them
        assert len(resumed.replay) == total
        assert np.array_equal(resumed.replay.rows[:adopted], expected)


def test_transfer_replay_from_a_run_without_replay_fails_clearly(tmp_path: Path) -> None:
    source = Path(train_corridor(str(tmp_path / "a"), None, 2, 0.0))
    shutil.rmtree(source / "replay")  # as in committed results
    spec = RunSpec(world="corridor.yaml", init_from=str(source))
    with pytest.raises(CheckpointError, match="transfer-replay.*no replay"):
        Trainer.start(tmp_path / "b", spec, tiny_config(transfer_replay=True), corridor_factory(), progress=False)
    assert not (tmp_path / "b").exists() or not any((tmp_path / "b").iterdir())
