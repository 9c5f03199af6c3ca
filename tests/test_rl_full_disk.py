"""A full disk (a real 1 MiB tmpfs, ENOSPC from the kernel) while saving a checkpoint: the save
fails with an OSError, no temp file stays behind, the previous checkpoint still loads; the train
command turns it into a one-line error. Skipped where mounting is impossible (not root)."""

from __future__ import annotations

import errno
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch

from sitl_bridge.rl.learner.checkpoint import load_checkpoint, save_checkpoint


@pytest.fixture
def tiny_disk(tmp_path: Path) -> Iterator[Path]:
    mount = tmp_path / "disk"
    mount.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mount)], capture_output=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.decode().strip()}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", str(mount)], check=True)


def test_checkpoint_save_on_full_disk_keeps_the_previous_one(tiny_disk: Path) -> None:
    small = {"w": torch.ones(16)}
    save_checkpoint(tiny_disk / "ckpt_1.safetensors", small, {"episode": 1})
    (tiny_disk / "filler").write_bytes(b"\0" * (1024 * 1024 - 64 * 1024))  # leave less than the next save
    with pytest.raises(OSError) as info:
        save_checkpoint(tiny_disk / "ckpt_2.safetensors", {"w": torch.ones(64 * 1024)}, {"episode": 2})
    assert info.value.errno == errno.ENOSPC
    assert sorted(p.name for p in tiny_disk.iterdir()) == ["ckpt_1.safetensors", "filler"]  # no temp file
    tensors, state = load_checkpoint(tiny_disk / "ckpt_1.safetensors")
    assert state["episode"] == 1 and torch.equal(tensors["w"], small["w"])


def test_train_on_full_disk_is_one_line(tiny_disk: Path) -> None:
    (tiny_disk / "filler").write_bytes(b"\0" * (1024 * 1024 - 8 * 1024))
    root = Path(__file__).parent.parent
    done = subprocess.run(["python3", "-m", "sitl_bridge", "train", "worlds/empty.yaml", "--out", str(tiny_disk),
                           "--episodes", "2", "--eval-episodes", "0", "--no-progress"],
                          cwd=root, capture_output=True, text=True, timeout=120)
    assert done.returncode in (1, 2), done.stderr
    errors = [line for line in done.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "Traceback" not in done.stderr, done.stderr
    assert not list(tiny_disk.rglob(".*.tmp*"))  # no temp file left behind
