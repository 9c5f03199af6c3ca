"""Where the report keeps its held-out greedy evaluation of each run: `greedy_eval.json` in the
run's sweep job folder (written by `results.evaluate_run`, read by the sections that need its
episodes), in a module of its own so that sections can read it without importing the results."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

GREEDY_FILE = "greedy_eval.json"
"""Cache of a run's report evaluation, in its sweep job folder (skipped when still valid)."""
THRESHOLD = 0.9
"""Greedy success that counts as learned (the `_90` of `episodes_to_90`, `seeds_90`)."""
EPISODE_MEASURES = "episodes"
"""Key of a `GREEDY_FILE` record: each held-out drone-episode's flight measures
(`rl.evaluation.flight_measures.episode_measures`); absent from records made before them."""


def held_out_record(run_dir: str | Path) -> dict[str, Any] | None:
    """The held-out evaluation of the run at `run_dir` (its job folder's `GREEDY_FILE`), or None."""
    path = Path(run_dir).parent / GREEDY_FILE
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) else None
