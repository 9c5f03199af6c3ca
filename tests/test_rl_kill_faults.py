"""kill -9 at seeded random points of training, evaluation and checkpoint writing, then --resume: the run ends
identical to an uninterrupted one of the same seed (episode log, every evaluation, best.json,
baseline, the best and every kept checkpoint's tensors and state).

The kills are real SIGKILLs of real processes: from outside, timed by the heartbeat's phase
(`greedy evaluation 3/6`, `constant action 2 ...`); from inside, at an exact point of an
atomic write (`test_rl_helpers.kill_when_replacing`), where a timed kill would rarely land.
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import torch
from test_rl_helpers import train_corridor

from sitl_bridge.rl.learner.checkpoint import BEST_CHECKPOINT, list_checkpoints, load_checkpoint
from sitl_bridge.rl.training.heartbeat import read_heartbeat

ROOT = Path(__file__).parent.parent
HELPER = Path(__file__).with_name("test_rl_helpers.py")
TIMES = ("wall_time_s", "cpu_time_s")
LOG_DIGESTS = ("log_bytes", "log_sha256")
"""Checkpoint state that covers the episode log's bytes, wall times included."""


def _jsonl(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def _without(record: dict, keys: tuple[str, ...]) -> dict:
    return {k: v for k, v in record.items() if k not in keys}


def _checkpoint(path: Path) -> tuple[dict, dict]:
    tensors, state = load_checkpoint(path)
    return tensors, _without(state, LOG_DIGESTS)


def assert_same_run(run: Path, reference: Path) -> None:
    """`run` (killed and resumed) holds what the uninterrupted `reference` holds."""
    assert [_without(r, TIMES) for r in _jsonl(run / "episodes.jsonl")] == \
        [_without(r, TIMES) for r in _jsonl(reference / "episodes.jsonl")]
    evals = [_without(r, TIMES) for r in _jsonl(run / "evals.jsonl")]
    assert evals and evals == [_without(r, TIMES) for r in _jsonl(reference / "evals.jsonl")]
    for name in ("best.json", "baseline.json"):
        assert json.loads((run / name).read_text()) == json.loads((reference / name).read_text()), name
    kept = [p.name for p in list_checkpoints(run / "checkpoints")]
    assert kept == [p.name for p in list_checkpoints(reference / "checkpoints")]
    for mine, theirs in [(run / BEST_CHECKPOINT, reference / BEST_CHECKPOINT),
                         *((run / "checkpoints" / n, reference / "checkpoints" / n) for n in kept)]:
        (tensors, state), (expected, expected_state) = _checkpoint(mine), _checkpoint(theirs)
        assert state == expected_state, mine.name
        assert tensors.keys() == expected.keys(), mine.name
        assert all(torch.equal(tensors[k], expected[k]) for k in tensors), mine.name


def kill_when(run_dir: Path, proc: subprocess.Popen, ready, timeout_s: float = 240.0) -> dict:
    """SIGKILL `proc` once its heartbeat satisfies `ready(beat)`; returns that heartbeat."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        beat = read_heartbeat(run_dir)
        if beat is not None and beat.get("pid") == proc.pid and ready(beat):
            proc.send_signal(signal.SIGKILL)
            assert proc.wait(timeout=60) == -signal.SIGKILL, "it finished before the kill"
            return beat
        assert proc.poll() is None, "it ended before the point to kill it at"
        time.sleep(0.005)
    raise AssertionError("the point to kill at never came")


# -- the trainer, kill -9 at seeded random points ----------------------------------------------
EPISODES = 8
CONFIG = {"eval_every": 2, "eval_episodes": 6, "checkpoints_kept": 3}
"""Evaluations after episodes 2, 4 and 6; the baseline flies 8 actions x 6 episodes."""


def _session(out: Path, run_dir: str, kill_at: str = "") -> subprocess.Popen:
    argv = [sys.executable, str(HELPER), str(out), run_dir, str(EPISODES), "0.005", json.dumps(CONFIG)]
    return subprocess.Popen([*argv, *([kill_at] if kill_at else [])], text=True, cwd=ROOT,
                            stdout=subprocess.PIPE if run_dir == "-" else subprocess.DEVNULL,  # prints a new run's dir
                            env={**os.environ, "PYTHONPATH": str(ROOT)})


def test_kill_9_in_training_evaluation_and_checkpoint_writes_then_resume_is_exact(tmp_path: Path) -> None:
    rng = random.Random(int(os.environ.get("SITL_BRIDGE_KILL_SEED", "20")))  # other seeds: other points
    reference = Path(train_corridor(str(tmp_path / "ref"), None, EPISODES, 0.0, **CONFIG))
    out = tmp_path / "killed"
    # 1. inside the checkpoint write after episode 1 or 2 (temp file written, or renamed in place)
    proc = _session(out, "-", f"ckpt_{rng.choice([1, 2]):07d}.safetensors:{rng.choice(['before', 'after'])}")
    run_dir = Path(proc.stdout.readline().strip())
    proc.stdout.close()
    assert proc.wait(timeout=240) == -signal.SIGKILL
    # 2. inside the first evaluation's best-checkpoint write
    proc = _session(out, str(run_dir), f"{rng.choice([BEST_CHECKPOINT, 'best.json'])}:{rng.choice(['before', 'after'])}")
    assert proc.wait(timeout=240) == -signal.SIGKILL
    # 3. during an evaluation: the first one's constant-action baseline (a random action's
    #    flights) or a later greedy evaluation (after a random episode of it)
    proc = _session(out, str(run_dir))
    if rng.random() < 0.5:
        action = rng.randrange(8)
        kill_when(run_dir, proc, lambda beat: beat["phase"].startswith(f"constant action {action} "))
    else:
        after, flown = rng.choice([4, 6]), rng.randint(1, 3)
        kill_when(run_dir, proc, lambda beat: beat["episode"] == after
                  and beat["phase"] == f"greedy evaluation {flown}/6")
    # 4. to the end
    proc = _session(out, str(run_dir))
    assert proc.wait(timeout=240) == 0
    assert not list(run_dir.glob("checkpoints/*.corrupt"))
    assert_same_run(run_dir, reference)


# -- `sitl-bridge train`, kill -9 during an evaluation -------------------------------------------
def _train_cli(out: Path, *argv: str) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "sitl_bridge", "train", *argv, "--out", str(out), "--no-progress"]
    return subprocess.Popen(cmd, cwd=ROOT, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True,
                            env={**os.environ, "PYTHONPATH": str(ROOT)})


def _run_dir_of(proc: subprocess.Popen) -> Path:
    before = []
    line = proc.stderr.readline()
    while line and not line.startswith("run directory: "):  # e.g. the numba compile notice
        before.append(line)
        line = proc.stderr.readline()
    assert line.startswith("run directory: "), "".join(before)
    threading.Thread(target=proc.stderr.read, daemon=True).start()  # drain: never block the child
    return Path(line[len("run directory: "):].split(" (resuming")[0].strip())


def kill_and_resume(tmp_path: Path, argv: list[str], ready, after_kill=None) -> tuple[Path, Path]:
    """Train `argv` twice at once with `python -m sitl_bridge train`: one run uninterrupted, the
    other killed with SIGKILL when `ready(heartbeat)` holds, checked by `after_kill(run_dir)`,
    then resumed. Returns (the resumed run's directory, the uninterrupted one's)."""
    uninterrupted = _train_cli(tmp_path / "ref", *argv)  # alongside the killed one (two cores)
    killed = _train_cli(tmp_path / "killed", *argv)
    try:
        run_dir = _run_dir_of(killed)
        kill_when(run_dir, killed, ready)
        if after_kill is not None:
            after_kill(run_dir)
        resumed = _train_cli(tmp_path / "unused", "--resume", str(run_dir))
        assert resumed.wait(timeout=300) == 0
        reference = _run_dir_of(uninterrupted)
        assert uninterrupted.wait(timeout=300) == 0
    finally:
        for proc in (uninterrupted, killed):
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    return run_dir, reference


def test_sitl_bridge_train_killed_during_an_evaluation_flies_it_again_on_resume(tmp_path: Path) -> None:
    args = ["worlds/empty.yaml", "--seed", "3", "--episodes", "3", "--eval-every", "1", "--eval-episodes", "4",
            "--layers", "2", "--hidden-units", "16"]

    def no_evaluation_done(run_dir: Path) -> None:
        assert not (run_dir / "evals.jsonl").exists()

    run_dir, reference = kill_and_resume(
        tmp_path, args, lambda beat: beat["episode"] == 1 and beat["phase"] == "greedy evaluation 1/4",
        no_evaluation_done)
    assert [e["after_episodes"] for e in _jsonl(run_dir / "evals.jsonl")] == [1, 2, 3]
    assert_same_run(run_dir, reference)
