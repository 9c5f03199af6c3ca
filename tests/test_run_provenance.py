"""A run records the git commit of the source tree it ran from (`run_dir.source_commit`)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import sitl_bridge
from sitl_bridge.rl.training.run_dir import source_commit


def test_source_commit_names_the_checkouts_head() -> None:
    root = Path(sitl_bridge.__file__).resolve().parents[1]
    head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True,
                          text=True, check=True).stdout.strip()
    commit = source_commit()
    assert commit is not None and commit.removesuffix("+dirty") == head
