"""A run's evaluation journal (`evals.jsonl`, one greedy evaluation per line) read back.

The line appended last by `Trainer.evaluate` is the mark that an evaluation is done: a run
killed before it flies that evaluation again on resume, one killed after it reads it back here,
and a resume from an older checkpoint drops the lines of the evaluations it will fly again.
"""

from __future__ import annotations

import json
from dataclasses import fields
from pathlib import Path
from typing import Any

from sitl_bridge.rl.common.atomic import atomic_write_bytes
from sitl_bridge.rl.evaluation.evaluate import EvalResult


def _lines(path: Path) -> list[tuple[bytes, dict[str, Any] | None]]:
    """Each line of the journal with its record (None for a line that is not one)."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return []
    lines = []
    for line in data.splitlines(keepends=True):
        try:
            record = json.loads(line)
        except ValueError:
            record = None
        lines.append((line, record if isinstance(record, dict) else None))
    return lines


def recorded_evaluation(path: Path, after_episodes: int, global_step: int) -> EvalResult | None:
    """The evaluation the journal holds for the state after `after_episodes` episodes and
    `global_step` steps (the last one when several), or None when it holds none."""
    names = {f.name for f in fields(EvalResult)}
    for _, record in reversed(_lines(path)):
        if (record is not None and record.get("after_episodes") == after_episodes
                and record.get("global_step") == global_step and names <= record.keys()):
            return EvalResult(**{name: record[name] for name in names})
    return None


def drop_evaluations_after(path: Path, episode: int) -> int:
    """Remove the journal's evaluations made after more than `episode` episodes (a run resumed
    from an older checkpoint flies them again); returns how many lines were removed."""
    lines = _lines(path)
    keep = [line for line, record in lines
            if not (record is not None and isinstance(record.get("after_episodes"), int)
                    and record["after_episodes"] > episode)]
    if len(keep) != len(lines):
        atomic_write_bytes(path, b"".join(keep))
    return len(lines) - len(keep)
