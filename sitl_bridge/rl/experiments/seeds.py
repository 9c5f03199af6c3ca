"""The report's evaluation seeds, in a module of their own: the results and every report section
use them, and the results module imports the sections."""

from __future__ import annotations

EVAL_SEED_BASE = 1_000_000
"""Evaluation seeds of the report: `eval_seeds(EVAL_SEED_BASE + seed, n)`, held out from the
periodic evaluations (`eval_seeds(seed, n)`) that picked the best checkpoint."""
