"""Damage to a run directory: a missing replay shard does not condemn the network, a run never
starts over its own history, garbage in the episode log is noticed, a sound checkpoint that does
not fit the run (another network size, a wrong state field) falls back to the previous one, and
an edited config.yaml is refused naming each key, condemning nothing."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from test_rl_helpers import corridor_factory, train_corridor

from sitl_bridge.errors import ConfigError
from sitl_bridge.rl.common.episode_log import read_records
from sitl_bridge.rl.learner.checkpoint import (
    CheckpointError,
    list_checkpoints,
    load_checkpoint,
    resolve_checkpoint,
    save_checkpoint,
)
from sitl_bridge.rl.learner.policy import policy_from_checkpoint
from sitl_bridge.rl.training.trainer import Trainer, read_run_records

EPISODES = 8
ROOT = Path(__file__).parent.parent


def comparable(records: list[dict]) -> list[tuple]:
    return [(r["episode"], r["drone"], r["actions"], r["outcome"], r["env_seed"]) for r in records]


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return Path(train_corridor(str(tmp_path_factory.mktemp("ref")), None, EPISODES, 0.0))


def copy_of(run: Path, tmp_path: Path) -> Path:
    target = tmp_path / run.name
    shutil.copytree(run, target)
    return target


def test_a_missing_replay_shard_keeps_the_network_and_the_history(reference: Path, tmp_path: Path) -> None:
    run = copy_of(reference, tmp_path)
    shards = sorted((run / "replay").glob("seg_*.bin"))
    assert shards
    shards[-1].unlink()
    warnings: list[str] = []
    with Trainer.resume(run, corridor_factory(), episodes=EPISODES + 2, progress=False,
                        warn=warnings.append) as trainer:
        assert trainer.episode == EPISODES  # resumed from the newest checkpoint, not from 0
        assert len(trainer.replay) == 0
        trainer.train()
    assert any("empty replay buffer" in w for w in warnings)
    assert not list(run.glob("checkpoints/*.corrupt"))
    episodes = [r["episode"] for r in read_run_records(run)]
    assert episodes == list(range(EPISODES + 2))  # no duplicate, no gap
    resolve_checkpoint(run)  # eval still finds a usable checkpoint
    # ... and the run resumes again normally afterwards (the new shards verify)
    with Trainer.resume(run, corridor_factory(), episodes=EPISODES + 3, progress=False) as trainer:
        assert len(trainer.replay) > 0
        trainer.train()
    assert [r["episode"] for r in read_run_records(run)] == list(range(EPISODES + 3))


def test_a_run_never_starts_over_its_own_history(reference: Path, tmp_path: Path) -> None:
    run = copy_of(reference, tmp_path)
    for path in list_checkpoints(run / "checkpoints"):
        path.rename(path.with_suffix(".corrupt"))
    before = (run / "episodes.jsonl").read_bytes()
    with pytest.raises(CheckpointError, match="refusing to start the run over its own history"):
        Trainer.resume(run, corridor_factory(), progress=False)
    assert (run / "episodes.jsonl").read_bytes() == before


def test_garbage_in_the_last_log_line_is_noticed_and_the_episode_flown_again(reference: Path,
                                                                              tmp_path: Path) -> None:
    run = copy_of(reference, tmp_path)
    log = run / "episodes.jsonl"
    data = bytearray(log.read_bytes())
    last_start = data.rindex(b"\n", 0, len(data) - 1) + 1
    data[last_start:-1] = b"#" * (len(data) - 1 - last_start)  # same length: the byte count matches
    log.write_bytes(bytes(data))
    warnings: list[str] = []
    with Trainer.resume(run, corridor_factory(), progress=False, warn=warnings.append) as trainer:
        assert trainer.episode == EPISODES - 1  # the previous checkpoint, whose log part is intact
        trainer.train()
    assert any("was changed since" in w for w in warnings)
    assert comparable(read_run_records(run)) == comparable(read_run_records(reference))


def test_reading_a_log_with_a_damaged_line_skips_it_with_a_warning(tmp_path: Path) -> None:
    log = tmp_path / "episodes.jsonl"
    good = json.dumps({"episode": 0, "drone": 0})
    log.write_text(f"{good}\nnot json at all\n{json.dumps({'episode': 1, 'drone': 0})}\n")
    warnings: list[str] = []
    records = read_records(log, warn=warnings.append)
    assert [r["episode"] for r in records] == [0, 1]
    assert warnings == [f"{log}: line 2 is not an episode record; skipped"]


def _refit(path: Path, tensors: dict, state: dict) -> None:
    """Write `path` again with the project's own save_checkpoint: a checkpoint that verifies."""
    save_checkpoint(path, tensors, state)
    load_checkpoint(path)


@pytest.mark.parametrize("unfit", ["a network of another size", "episode 'x'", "no 'updates'"])
def test_a_sound_checkpoint_that_does_not_fit_falls_back_to_the_previous(reference: Path, tmp_path: Path,
                                                                        unfit: str) -> None:
    run = copy_of(reference, tmp_path)
    newest = list_checkpoints(run / "checkpoints")[0]
    tensors, state = load_checkpoint(newest)
    if unfit == "a network of another size":
        other = Path(train_corridor(str(tmp_path / "other"), None, 1, 0.0, hidden_units=24))
        tensors, _ = load_checkpoint(list_checkpoints(other / "checkpoints")[0])
    elif unfit == "episode 'x'":
        state["episode"] = "x"
    else:
        del state["updates"]
    _refit(newest, tensors, state)

    warnings: list[str] = []
    with Trainer.resume(run, corridor_factory(), progress=False, warn=warnings.append) as trainer:
        assert trainer.episode == EPISODES - 1  # the previous checkpoint
        trainer.train()
    assert len(warnings) == 1 and "\n" not in warnings[0], warnings
    assert newest.name in warnings[0] and "unusable" in warnings[0] and "falling back" in warnings[0]
    assert comparable(read_run_records(run)) == comparable(read_run_records(reference))
    if unfit == "no 'updates'":
        return  # eval needs only the network and its episode count: that checkpoint flies
    # eval falls back the same way, and names a checkpoint file that does not fit in one line
    _refit(newest, tensors, state)
    assert policy_from_checkpoint(run, latest=True).episode == EPISODES - 1
    with pytest.raises(CheckpointError, match="unusable content") as info:
        policy_from_checkpoint(newest)
    assert "\n" not in str(info.value)


def test_eval_of_a_checkpoint_that_does_not_fit_is_one_line(reference: Path, tmp_path: Path) -> None:
    run = copy_of(reference, tmp_path)
    newest = list_checkpoints(run / "checkpoints")[0]
    tensors, state = load_checkpoint(newest)
    _refit(newest, tensors, {**state, "network": {**state["network"], "hidden_units": 24}})
    proc = subprocess.run([sys.executable, "-m", "sitl_bridge", "eval", str(newest), "--world", "worlds/empty.yaml",
                           "--episodes", "1"], cwd=ROOT, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.startswith("error: ") and "size mismatch" in proc.stderr, proc.stderr
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr


def test_an_edited_config_is_refused_naming_each_key_and_condemns_nothing(reference: Path, tmp_path: Path) -> None:
    run = copy_of(reference, tmp_path)
    config_file = run / "config.yaml"
    original = config_file.read_text()
    edited = yaml.safe_load(original)
    edited.update(hidden_units=8, gamma=0.5)
    config_file.write_text(yaml.safe_dump(edited, sort_keys=False))
    files = sorted(p.name for p in run.rglob("*"))
    with pytest.raises(ConfigError) as info:
        Trainer.resume(run, corridor_factory(), progress=False)
    message = str(info.value)
    assert "\n" not in message
    assert "config.yaml differs from the run's checkpoints in: gamma (0.9 -> 0.5), hidden_units (16 -> 8)" in message
    assert sorted(p.name for p in run.rglob("*")) == files  # nothing renamed *.corrupt, nothing added
    config_file.write_text(original)  # put back: the run resumes where it was
    with Trainer.resume(run, corridor_factory(), episodes=EPISODES + 1, progress=False) as trainer:
        assert trainer.episode == EPISODES
        trainer.train()
    assert [r["episode"] for r in read_run_records(run)] == list(range(EPISODES + 1))
