#!/usr/bin/env python3
"""Soak test (not in CI: minutes long): `sitl-bridge train --watchdog` for N minutes while a
random fault is injected every few episodes; reports faults injected, recoveries and episodes
lost or duplicated.

Run from the repository root (it trains on the `direct` backend; a few minutes on a laptop):

    python3 tools/soak.py --minutes 5 [--every 3] [--world worlds/empty.yaml] [--out /tmp/soak] [--seed 0]

Faults, one at random each `--every` episodes once the restarted child has beaten: SIGKILL of
the training child, SIGSTOP (frozen: the watchdog's `--freeze-timeout 10` must notice), garbage
appended to episodes.jsonl's last line (then SIGKILL, so the resume must notice it), a deleted
replay shard (then SIGKILL).

What it checks (exit 0 only when all hold): the episode log, read after the soak, holds every
episode index from 0 to the last exactly once (none lost, none flown twice by a resume), and
the watchdog restarted the child at least once per injected fault (the last may still be
pending when the time is up). It prints the counts: faults per kind, restarts per reason,
episodes completed, missing and duplicated indices, the watchdog's exit code. The run directory
(`--out`, default a fresh temp dir) keeps the run and `soak-watchdog.log` for a look after.
"""
from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from sitl_bridge.rl.training.heartbeat import read_heartbeat  # noqa: E402

FAULTS = ("sigkill", "sigstop", "corrupt_last_line", "delete_shard")


def inject(fault: str, run_dir: Path, pid: int) -> None:
    if fault == "sigstop":
        os.kill(pid, signal.SIGSTOP)
        return
    if fault == "corrupt_last_line":
        with open(run_dir / "episodes.jsonl", "ab") as handle:
            handle.write(b'{"episode": garbage\xff')
    elif fault == "delete_shard":
        shards = sorted((run_dir / "replay").glob("*"))
        if shards:
            random.choice(shards).unlink()
    os.kill(pid, signal.SIGKILL)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--minutes", type=float, default=5.0)
    parser.add_argument("--every", type=int, default=3, help="a fault every this many episodes")
    parser.add_argument("--world", default="worlds/empty.yaml")
    parser.add_argument("--out", default=None)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    random.seed(args.seed)
    out = Path(args.out or tempfile.mkdtemp(prefix="soak-"))
    out.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "sitl_bridge", "train", args.world, "--watchdog", "--out", str(out),
           "--episodes", "100000", "--eval-episodes", "0", "--no-progress", "--freeze-timeout", "10",
           "--max-restarts-per-hour", "1000"]
    log = open(out / "soak-watchdog.log", "w")  # noqa: SIM115 -- open for the whole soak
    proc = subprocess.Popen(cmd, cwd=ROOT, stderr=log, env={**os.environ, "PYTHONPATH": str(ROOT)})
    injected: Counter[str] = Counter()
    end = time.monotonic() + 60 * args.minutes
    next_fault_at, last_pid = args.every, None
    run_dir: Path | None = None
    try:
        while time.monotonic() < end and proc.poll() is None:
            time.sleep(0.2)  # polling pace
            run_dir = run_dir or next((d for d in out.glob("*/") if (d / "heartbeat.json").exists()), None)
            beat = read_heartbeat(run_dir) if run_dir else None
            if beat is None or beat["episode"] < next_fault_at or beat["pid"] == last_pid:
                continue
            fault = random.choice(FAULTS)
            inject(fault, run_dir, beat["pid"])
            injected[fault] += 1
            last_pid = beat["pid"]  # the next fault waits for the restarted child
            next_fault_at = beat["episode"] + args.every
            print(f"[{time.strftime('%H:%M:%S')}] episode {beat['episode']}: injected {fault}", flush=True)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=60)
    if run_dir is None:
        print(f"soak: training never started; see {out}/soak-watchdog.log")
        return 1
    episodes = [json.loads(line)["episode"] for line in (run_dir / "episodes.jsonl").read_text().splitlines()]
    restarts = [json.loads(line) for line in (run_dir / "watchdog.jsonl").read_text().splitlines()] \
        if (run_dir / "watchdog.jsonl").exists() else []
    counts = Counter(episodes)
    missing = sorted(set(range(max(episodes) + 1)) - set(counts)) if episodes else []
    duplicated = sorted(e for e, n in counts.items() if n > 1)
    print(f"soak: {args.minutes:g} min, run {run_dir}")
    print(f"  faults injected: {sum(injected.values())} ({dict(injected)})")
    print(f"  recoveries (watchdog restarts): {len(restarts)} ({dict(Counter(r['reason'] for r in restarts))})")
    print(f"  episodes completed: {len(counts)}; missing indices: {missing or 'none'}; "
          f"duplicated indices: {duplicated or 'none'}")
    print(f"  watchdog exit code {proc.returncode}")
    return 0 if not missing and not duplicated and len(restarts) >= sum(injected.values()) - 1 else 1


if __name__ == "__main__":
    sys.exit(main())
