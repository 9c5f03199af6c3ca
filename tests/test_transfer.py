"""`sitl-bridge transfer`: a trained policy evaluated greedily on several backends, same seeds,
with Wilson 95 % intervals (issue 15 item 3). The px4 column needs PX4_BIN."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import pick_free_instances

from sitl_bridge.rl.stats import wilson_interval

WORLD = str(Path(__file__).resolve().parent.parent / "worlds" / "empty.yaml")


def test_wilson_interval() -> None:
    assert wilson_interval(0, 10)[0] == 0.0 and 0.25 < wilson_interval(0, 10)[1] < 0.35
    lo, hi = wilson_interval(10, 20)
    assert lo == pytest.approx(1 - hi) and 0.29 < lo < 0.31  # symmetric around 0.5
    assert wilson_interval(0, 0) == (0.0, 1.0)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("runs")
    train = subprocess.run(
        [sys.executable, "-m", "sitl_bridge", "train", WORLD, "--episodes", "2", "--out", str(out),
         "--batch-size", "16", "--layers", "2", "--hidden-units", "16", "--eval-every", "0",
         "--eval-episodes", "0", "--no-progress"], capture_output=True, text=True, timeout=240)
    assert train.returncode == 0, train.stdout + train.stderr
    (run,) = [p for p in out.iterdir() if p.is_dir()]
    return run


def _transfer(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sitl_bridge", "transfer", *args],
                          capture_output=True, text=True, timeout=400)


def test_transfer_direct_and_stub_same_seeds(run_dir: Path, tmp_path: Path) -> None:
    table = tmp_path / "transfer.json"
    result = _transfer(str(run_dir), "--autopilots", "direct,stub", "--episodes", "2",
                       "--instance-base", str(pick_free_instances(1)), "--json", str(table))
    assert result.returncode == 0, result.stdout + result.stderr
    rows = json.loads(table.read_text())
    assert [r["autopilot"] for r in rows] == ["direct", "stub"]
    for row in rows:
        assert row["drone_episodes"] == 2
        lo, hi = row["success_ci95"]
        assert lo <= row["success"] <= hi
    assert "direct" in result.stdout and "stub" in result.stdout and "success" in result.stdout


def test_transfer_on_px4(run_dir: Path, px4_bin: str, tmp_path: Path) -> None:
    table = tmp_path / "transfer.json"
    result = _transfer(str(run_dir), "--autopilots", "direct,px4", "--episodes", "2",
                       "--px4-bin", px4_bin, "--json", str(table))
    assert result.returncode == 0, result.stdout + result.stderr
    assert [r["autopilot"] for r in json.loads(table.read_text())] == ["direct", "px4"]


def test_unknown_backend_is_one_line(run_dir: Path) -> None:
    result = _transfer(str(run_dir), "--autopilots", "direct,ardupilot")
    assert result.returncode == 2 and result.stderr.count("\n") == 1 and "ardupilot" in result.stderr
