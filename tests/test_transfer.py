"""`sitl-bridge transfer`: a trained policy evaluated greedily on several backends, same seeds,
with Wilson 95 % intervals. The px4 column needs PX4_BIN."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import pick_free_instances

from sitl_bridge.rl.common.stats import wilson_interval
from sitl_bridge.rl.experiments.backend_transfer import (
    BackendFlight,
    differs,
    pooled,
    same_actions,
    summary,
    why_differ,
)

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
    assert "same_actions_as" not in rows[0] and rows[1]["same_actions_as"]["compared"] == 2
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


def _flight(autopilot: str, outcomes: list[str], steps: list[int], step_m: list[float],
            actions: list[list[int]]) -> BackendFlight:
    return BackendFlight(autopilot, len(outcomes), 0, outcomes, steps, step_m, actions)


def test_why_two_backends_differ_comes_from_the_episodes() -> None:
    """Known episodes: on px4 two of four goals become timeouts, the goals that remain take
    longer and the drone covers less ground per step; one episode repeats direct's actions."""
    direct = _flight("direct", ["goal"] * 4, [8, 8, 10, 10], [1.0, 1.0, 1.0, 1.0],
                     [[3] * 8, [3] * 8, [1] * 10, [1] * 10])
    px4 = _flight("px4", ["goal", "goal", "timeout", "timeout"], [8, 12, 30, 30], [1.0, 0.5, 0.5, 0.5],
                  [[3] * 8, [3, 3, 2] + [3] * 9, [1, 1, 1, 2] + [1] * 26, [1] * 30])
    assert summary(direct)["success"] == 1.0 and summary(px4)["success"] == 0.5
    assert summary(px4)["mean_steps_success"] == 10.0 and summary(px4)["outcomes"]["timeout"] == 2
    assert differs(summary(direct), summary(px4)) and not differs(summary(direct), summary(direct))
    same = same_actions(direct, px4)
    # the second parts at step 3, the third at 4, the fourth flies on after direct's 10 steps: 11
    assert same == {"compared": 4, "identical": 1, "first_difference_median": 4}
    why = why_differ("direct", direct, px4)
    assert why.startswith("success 50 % vs 100 % on direct (-50 points)")
    assert "goal 4 -> 2, timeout 0 -> 2" in why and "10.0 steps vs 9.0 (+11 %)" in why
    assert "0.62 m flown per step vs 1.00 (-38 %)" in why
    assert "same actions in 1 of 4 drone-episodes, the others part at step 4 (median)" in why


def test_pooled_flights_keep_every_drone_episode() -> None:
    a = _flight("stub", ["goal", "crash"], [5, 3], [1.0, 1.0], [[0] * 5, [1] * 3])
    b = _flight("stub", ["goal", "goal"], [7, 9], [1.0, 1.0], [[0] * 7, [0] * 9])
    total = summary(pooled([a, b]))
    assert total["drone_episodes"] == 4 and total["success"] == 0.75 and total["collision"] == 0.25
    assert total["success_ci95"] == list(wilson_interval(3, 4)) and total["mean_steps_success"] == 7.0
    assert BackendFlight.from_dict(a.to_dict()) == a


def test_unknown_backend_is_one_line(run_dir: Path) -> None:
    result = _transfer(str(run_dir), "--autopilots", "direct,ardupilot")
    assert result.returncode == 2 and result.stderr.count("\n") == 1 and "ardupilot" in result.stderr
