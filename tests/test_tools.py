"""The documented tool commands (docs/benchmarks.md) work from any working directory of a clone."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
STUB_RESPONSE = REPO / "tools" / "stub_response.py"


def test_stub_response_runs_on_the_shipped_recording(tmp_path: Path) -> None:
    result = subprocess.run([sys.executable, str(STUB_RESPONSE)], cwd=tmp_path,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert "along-axis displacement per 1 s step" in result.stdout
    for kind in ("first", "repeated", "vertical", "coast"):
        assert f"  {kind}" in result.stdout


def test_stub_response_missing_recording_is_one_line(tmp_path: Path) -> None:
    result = subprocess.run([sys.executable, str(STUB_RESPONSE), "--csv", str(tmp_path / "none.csv")],
                            cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0
    assert "no such PX4 recording" in result.stderr
