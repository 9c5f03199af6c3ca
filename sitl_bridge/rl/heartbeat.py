"""Training heartbeat: a small JSON file in the run directory that a watchdog reads.

Written atomically after every episode (cheap: one small file); a watchdog that sees no new
heartbeat for T seconds treats the learner/simulator as frozen.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

from sitl_bridge.rl.atomic import atomic_write_json

HEARTBEAT_FILE = "heartbeat.json"


def write_heartbeat(run_dir: str | Path, episode: int, global_step: int) -> None:
    """Record that training is alive at `episode`; `global_step` (environment steps) is the
    simulated-time counter, `wall_time` and `pid` tell a watchdog who beat and when."""
    atomic_write_json(Path(run_dir) / HEARTBEAT_FILE, {
        "episode": episode, "global_step": global_step, "wall_time": time.time(), "pid": os.getpid()})


def read_heartbeat(run_dir: str | Path) -> dict[str, Any] | None:
    """The last heartbeat, or None when there is none (yet) or it cannot be read."""
    try:
        value = json.loads((Path(run_dir) / HEARTBEAT_FILE).read_text())
    except (OSError, ValueError):
        return None
    return value if isinstance(value, dict) else None
