"""The committed results stay light: every clone carries them.

A run in `docs/results/` keeps what its report and pictures need (run files, evaluations, the
policy-only export of its best network, its episode log compressed); training checkpoints and
replay stay on the machine that trained (`tools/slim_results.py` slims a results tree). The
report is rebuilt from these files alone (`tests/test_experiment.py` checks the rebuild).
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from sitl_bridge.rl.learner.policy_file import is_policy_file

REPO = Path(__file__).resolve().parent.parent
RESULTS = "docs/results"
BUDGET_BYTES = 40_000_000


@pytest.fixture(scope="module")
def tracked() -> list[Path]:
    listing = subprocess.run(["git", "-C", str(REPO), "ls-files", "-z", RESULTS], capture_output=True)
    if listing.returncode != 0:
        pytest.skip("not a git checkout: the committed results cannot be listed")
    files = [REPO / name for name in listing.stdout.decode().split("\0") if name]
    assert files, f"nothing tracked under {RESULTS}"
    return files


def test_the_committed_results_fit_the_budget(tracked: list[Path]) -> None:
    total = sum(path.stat().st_size for path in tracked)
    assert total <= BUDGET_BYTES, f"{RESULTS} holds {total:,} bytes, over its {BUDGET_BYTES:,}: slim it"


def test_committed_runs_keep_policies_and_compressed_logs_only(tracked: list[Path]) -> None:
    parts = {part for path in tracked for part in path.relative_to(REPO).parts}
    assert not parts & {"checkpoints", "replay", "episodes.jsonl"}, "training state committed: slim it"
    networks = [path for path in tracked if path.suffix == ".safetensors"]
    assert networks
    assert [path for path in networks if not is_policy_file(path)] == [], "a training checkpoint, not a policy export"
