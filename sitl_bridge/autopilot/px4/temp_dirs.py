"""Temporary PX4 run directories (`$TMPDIR/sitl-bridge-px4-*`) that a killed owner leaves.

A session without `run_dir` keeps PX4's working directories in a temp dir it removes on
close. A SIGKILLed owner cannot, so each such dir names its owner (pid and the kernel's start
time of that process, which tells a reused pid apart) and the next one made removes every
dir whose owner is gone.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path

PREFIX = "sitl-bridge-px4-"
OWNER_FILE = "owner"


def _start_time(pid: int) -> str | None:
    """Field 22 of /proc/PID/stat (start time in clock ticks since boot); None if gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return stat.rsplit(")", 1)[1].split()[19]  # fields after "(comm)" start at field 3


def make_temp_run_dir() -> Path:
    """A new temp run dir owned by this process (stale ones removed first)."""
    remove_stale_run_dirs()
    path = Path(tempfile.mkdtemp(prefix=PREFIX))
    (path / OWNER_FILE).write_text(f"{os.getpid()} {_start_time(os.getpid())}\n")
    return path


def remove_stale_run_dirs(root: str | os.PathLike[str] | None = None) -> list[Path]:
    """Remove the temp run dirs under `root` (default: the temp dir) whose owner process no
    longer runs; dirs without an owner file (not ours, or being made) are left. Returns them."""
    removed = []
    for path in Path(root or tempfile.gettempdir()).glob(PREFIX + "*"):
        try:
            pid_text, start = (path / OWNER_FILE).read_text().split()
            pid = int(pid_text)
        except (OSError, ValueError):
            continue
        if _start_time(pid) != start:
            with contextlib.suppress(OSError):
                shutil.rmtree(path)
                removed.append(path)
    return removed
