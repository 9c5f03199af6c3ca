"""`sitl-bridge train --watchdog` with real processes: the training child is SIGKILLed and then
SIGSTOPped (frozen); the watchdog tears it down, resumes from the last checkpoint, and the run
ends with every episode index exactly once (no gap, no duplicate). Plus: the restart limit."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from sitl_bridge.rl.training.heartbeat import read_heartbeat
from sitl_bridge.rl.training.watchdog import _resume_argv

ROOT = Path(__file__).parent.parent
EPISODES = 10


def start_watchdog(out: Path, *extra: str) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "sitl_bridge", "train", "worlds/empty.yaml", "--watchdog", "--out", str(out),
           "--episodes", str(EPISODES), "--eval-episodes", "0", "--no-progress", *extra]
    return subprocess.Popen(cmd, cwd=ROOT, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": str(ROOT)})


def wait_for_episode(out: Path, episode: int, proc: subprocess.Popen, timeout_s: float = 180.0) -> dict:
    """The heartbeat once training passed `episode` (the watchdog must still be running)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for run_dir in out.glob("*/"):
            beat = read_heartbeat(run_dir)
            if beat is not None and beat["episode"] >= episode:
                return beat
        assert proc.poll() is None, proc.stderr.read()
        time.sleep(0.05)
    raise AssertionError(f"training never reached episode {episode}")


def test_watchdog_recovers_from_sigkill_and_sigstop(tmp_path: Path) -> None:
    proc = start_watchdog(tmp_path, "--freeze-timeout", "8")
    try:
        os.kill(wait_for_episode(tmp_path, 3, proc)["pid"], signal.SIGKILL)
        beat = wait_for_episode(tmp_path, 6, proc)
        os.kill(beat["pid"], signal.SIGSTOP)  # frozen: alive but no heartbeat progress
        _, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    (run_dir,) = tmp_path.glob("*/")
    episodes = [json.loads(line)["episode"] for line in (run_dir / "episodes.jsonl").read_text().splitlines()]
    assert episodes == list(range(EPISODES))  # one drone: each index exactly once, in order
    restarts = [json.loads(line) for line in (run_dir / "watchdog.jsonl").read_text().splitlines()]
    assert [r["reason"] for r in restarts] == ["killed by signal 9", "no heartbeat progress for 8 s (frozen)"]
    assert "watchdog: 2 restart(s)" in err
    with pytest.raises(ProcessLookupError):  # the stopped child was torn down, not left behind
        os.kill(beat["pid"], 0)


def test_watchdog_stops_after_max_restarts_per_hour(tmp_path: Path) -> None:
    proc = start_watchdog(tmp_path, "--max-restarts-per-hour", "0")
    try:
        os.kill(wait_for_episode(tmp_path, 1, proc)["pid"], signal.SIGKILL)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 1
    assert "reached --max-restarts-per-hour 0" in err
    (run_dir,) = tmp_path.glob("*/")
    assert json.loads((run_dir / "watchdog.jsonl").read_text())["gave_up"] is True


def test_resume_argv_keeps_only_what_resume_accepts() -> None:
    argv = ["worlds/empty.yaml", "--out", "runs", "--episodes", "9", "--seed", "3", "--no-progress", "--gamma=0.9"]
    assert _resume_argv(argv, Path("runs/x")) == ["--resume", "runs/x", "--episodes", "9", "--no-progress"]


def test_an_evaluation_longer_than_the_freeze_timeout_is_no_freeze(tmp_path: Path) -> None:
    """The heartbeat beats inside the periodic evaluation and the constant-action baseline (8
    actions x 25 episodes, 200 flights: 20 s and more), far longer than the freeze timeout here
    (which still leaves a loaded machine room for a training episode or the child's exit)."""
    cmd = [sys.executable, "-m", "sitl_bridge", "train", "worlds/empty.yaml", "--watchdog", "--out", str(tmp_path),
           "--episodes", "2", "--eval-every", "1", "--eval-episodes", "25", "--no-progress",
           "--freeze-timeout", "8", "--max-restarts-per-hour", "0"]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=400,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert proc.returncode == 0, proc.stderr
    assert "watchdog: 0 restart(s)" in proc.stderr
    (run_dir,) = tmp_path.glob("*/")
    assert not (run_dir / "watchdog.jsonl").exists()
    evals = [json.loads(line) for line in (run_dir / "evals.jsonl").read_text().splitlines()]
    assert [e["after_episodes"] for e in evals] == [1, 2]  # the periodic one and the final one
    assert (run_dir / "baseline.json").is_file()
    assert read_heartbeat(run_dir)["phase"] == "greedy evaluation 25/25"  # the final evaluation's last beat
