"""Fine-tuning on real PX4: `train --autopilot px4 --init-from RUN_DIR`
continues a `direct`-trained network on PX4, checkpointed and resumable like any run.
Skipped without PX4_BIN."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from test_rl_cli import EMPTY, TINY, cli, only_run

from sitl_bridge.rl.common.episode_log import read_records
from sitl_bridge.rl.learner.checkpoint import list_checkpoints, load_checkpoint


@pytest.mark.px4
@pytest.mark.timeout(600)
def test_train_on_px4_from_a_direct_run_checkpoints_and_resumes(px4_bin: str, tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PX4_BIN", px4_bin)
    tiny = [*TINY[:-2], "0", "--no-progress"]  # no evaluation episodes (PX4 time is precious)
    assert cli("train", EMPTY, "--episodes", "1", "--seed", "3", "--out", str(tmp_path / "direct"), *tiny) == 0
    source = only_run(tmp_path / "direct")
    source_weights, _ = load_checkpoint(list_checkpoints(source / "checkpoints")[0])

    assert cli("train", EMPTY, "--autopilot", "px4", "--episodes", "2", "--seed", "4",
               "--out", str(tmp_path / "px4"), "--init-from", str(source), *tiny) == 0
    run = only_run(tmp_path / "px4")
    spec = json.loads((run / "run.json").read_text())
    assert spec["autopilot"] == "px4" and Path(spec["init_from"]).resolve() == source.resolve()
    assert [r["episode"] for r in read_records(run / "episodes.jsonl")] == [0, 1]
    first = list_checkpoints(run / "checkpoints")
    assert first and first[0].name == "ckpt_0000002.safetensors"
    tuned, _ = load_checkpoint(first[0])
    # the direct network was the start (same shapes), and PX4 episodes trained it further
    assert tuned["online.net.0.weight"].shape == source_weights["online.net.0.weight"].shape
    assert not torch.equal(tuned["online.net.0.weight"], source_weights["online.net.0.weight"])

    assert cli("train", "--resume", str(run), "--episodes", "3", "--no-progress") == 0
    records = read_records(run / "episodes.jsonl")
    assert [r["episode"] for r in records] == [0, 1, 2]  # continued, no gap, no duplicate
    assert list_checkpoints(run / "checkpoints")[0].name == "ckpt_0000003.safetensors"
