"""A/B of the `px4` env step between two source trees, alternating, in one run.

Each round runs `tools/px4_step_profile.py` (from this tree) for tree A then tree B (the order
flips every round, so a load drift favours neither), each in a fresh process with PYTHONPATH
set to that tree (so its px4_params/px4-rc.mavlink too): real PX4 SITL (PX4_BIN), `--steps`
env steps of a constant action. Reports per tree the median over the rounds of env steps/s,
wall ms, CPU ms per env step of our process (and its lockstep and MAVSDK threads) and of PX4,
and the B/A ratios. On a shared machine the CPU figures are the fairer comparison.

Usage: PX4_BIN=... python tools/px4_ab.py OLD_TREE NEW_TREE [--rounds 5] [--steps 60]
       [--world empty.yaml] [--json F]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

PROFILE = Path(__file__).resolve().parent / "px4_step_profile.py"
FIGURES = ("steps_per_s", "wall_ms", "ours_cpu_ms", "sim_thread_cpu_ms", "mavsdk_cpu_ms", "px4_cpu_ms")


def measure(tree: Path, steps: int, world: str) -> dict[str, float]:
    """One profile run of `tree` (a fresh process)."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    for attempt in range(3):
        with tempfile.NamedTemporaryFile(suffix=".json") as out:
            done = subprocess.run([sys.executable, str(PROFILE), "--steps", str(steps), "--world", world,
                                   "--json", out.name], cwd=tree, env=env, capture_output=True, text=True, timeout=900)
            if done.returncode == 0:
                result = json.loads(Path(out.name).read_text())
                break
        # a failed run (e.g. a PX4 start on a busy machine) is reported and run again
        print(f"{tree}: run {attempt + 1} failed:\n{done.stderr[-3000:]}", file=sys.stderr, flush=True)
    else:
        raise RuntimeError(f"{tree}: the profile failed 3 times")
    threads = result["threads_cpu_ms"]
    return {
        "steps_per_s": result["steps_per_s"], "wall_ms": result["wall_ms"],
        "ours_cpu_ms": result["ours_cpu_ms"], "px4_cpu_ms": result["px4_cpu_ms"],
        "sim_thread_cpu_ms": threads.get("sitl-bridge-sim", 0.0),
        # MAVSDK's threads are the native ones (unnamed in Python)
        "mavsdk_cpu_ms": sum(v for k, v in threads.items() if k.startswith("native:")),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("old", type=Path)
    parser.add_argument("new", type=Path)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--world", default="empty.yaml")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    trees = {"A": args.old.resolve(), "B": args.new.resolve()}
    runs: dict[str, list[dict[str, float]]] = {"A": [], "B": []}
    for round_ in range(args.rounds):
        order = ("A", "B") if round_ % 2 == 0 else ("B", "A")
        for label in order:
            figures = measure(trees[label], args.steps, args.world)
            runs[label].append(figures)
            print(f"round {round_ + 1} {label}: " + ", ".join(f"{k} {v:.2f}" for k, v in figures.items()), flush=True)
    medians: dict[str, Any] = {label: {k: statistics.median(r[k] for r in rs) for k in FIGURES}
                               for label, rs in runs.items()}
    ratios = {k: medians["B"][k] / medians["A"][k] if medians["A"][k] else float("nan") for k in FIGURES}
    report = {"trees": {k: str(v) for k, v in trees.items()}, "rounds": args.rounds, "steps": args.steps,
              "world": args.world, "median": medians, "B_over_A": ratios, "runs": runs}
    for k in FIGURES:
        print(f"{k:>18}: A {medians['A'][k]:8.2f}   B {medians['B'][k]:8.2f}   B/A {ratios[k]:.3f}")
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
