"""Damage to a run directory (issue 14 items 4-5): a missing replay shard does not condemn the
network, a run never starts over its own history, and garbage in the episode log is noticed."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from test_rl_helpers import corridor_factory, train_corridor

from sitl_bridge.rl.checkpoint import CheckpointError, list_checkpoints, resolve_checkpoint
from sitl_bridge.rl.episode_log import read_records
from sitl_bridge.rl.trainer import Trainer, read_run_records

EPISODES = 8


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
