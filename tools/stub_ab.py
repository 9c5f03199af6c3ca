"""A/B of the stub protocol path between two source trees, alternating, in one run.

Each round runs, for tree A then tree B (the order flips every round, so a load drift
favours neither), in a fresh process with PYTHONPATH set to that tree:

* `tools/stub_step_profile.py` (from this tree): thread CPU us per physics step, one vehicle
  flying in OFFBOARD (the median of its own repetitions);
* the bench suite's `stub` case (`sitl_bridge.bench.suite._env_case`, random actions on the
  obstacle scenario, speed 0) with a bare-pybullet reference measured right before it, as
  `bench --quick` does: real-time factor and fraction of bare.

Reports the median over the rounds per tree and the B/A ratios.

Usage: python tools/stub_ab.py OLD_TREE NEW_TREE [--rounds 5] [--seconds 10] [--json F]
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

PROFILE = Path(__file__).resolve().parent / "stub_step_profile.py"

# the suite's stub case at `--quick` size (reps, warm-up and sim seconds), one bare reference
_BENCH = """
import json, statistics, sys
from sitl_bridge.bench.physics import bare_pybullet_rtf
from sitl_bridge.bench.suite import SIZES, _env_case
size = SIZES["quick"]
bare = statistics.median(bare_pybullet_rtf(size.bare_s)[0] for _ in range(size.reps))
figures, _ = _env_case("stub", size, bare)
json.dump({"rtf": figures["rtf"]["median"], "fraction_of_bare": figures["fraction_of_bare"]["median"],
           "bare": bare}, sys.stdout)
"""


def _run(tree: Path, args: list[str]) -> str:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    done = subprocess.run([sys.executable, *args], cwd=tree, env=env, capture_output=True, text=True,
                          timeout=900, check=True)
    return done.stdout


def measure(tree: Path, seconds: float) -> dict[str, Any]:
    """Thread CPU per step (profile tool) and the bench's stub figures for `tree`."""
    with tempfile.NamedTemporaryFile(suffix=".json") as out:
        _run(tree, [str(PROFILE), "--seconds", str(seconds), "--reps", "3", "--json", out.name])
        profile = json.loads(Path(out.name).read_text())
    bench = json.loads(_run(tree, ["-c", _BENCH]).strip().splitlines()[-1])
    return {"thread_cpu_us": profile["thread_cpu_us"]["median"], "cpu_us_per_step": profile["cpu_us_per_step"],
            **{f"bench_{k}": v for k, v in bench.items()}}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("old", type=Path)
    parser.add_argument("new", type=Path)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--seconds", type=float, default=10.0, help="simulated seconds per profile run")
    parser.add_argument("--json", help="write every round's figures to this file")
    args = parser.parse_args()
    trees = {"A": args.old.resolve(), "B": args.new.resolve()}
    rounds: dict[str, list[dict[str, Any]]] = {"A": [], "B": []}
    for i in range(args.rounds):
        for name in ("A", "B") if i % 2 == 0 else ("B", "A"):
            rounds[name].append(measure(trees[name], args.seconds))
            r = rounds[name][-1]
            print(f"round {i} {name}: {r['thread_cpu_us']:.1f} us/step CPU, bench stub {r['bench_rtf']:.1f}x "
                  f"({r['bench_fraction_of_bare']:.3f} of bare {r['bench_bare']:.0f}x), load {os.getloadavg()[0]:.1f}",
                  flush=True)
    summary: dict[str, Any] = {}
    for key in ("thread_cpu_us", "bench_rtf", "bench_fraction_of_bare"):
        a = statistics.median(r[key] for r in rounds["A"])
        b = statistics.median(r[key] for r in rounds["B"])
        summary[key] = {"A": a, "B": b, "B_over_A": b / a}
        print(f"{key:<24} A {a:8.3f}  B {b:8.3f}  B/A {b / a:.3f}")
    components = rounds["A"][0]["cpu_us_per_step"].keys() | rounds["B"][0]["cpu_us_per_step"].keys()
    print("thread CPU us per step by component (median over rounds):")
    for name in sorted(components):
        a = statistics.median(r["cpu_us_per_step"].get(name, 0.0) for r in rounds["A"])
        b = statistics.median(r["cpu_us_per_step"].get(name, 0.0) for r in rounds["B"])
        summary.setdefault("components", {})[name] = {"A": a, "B": b}
        print(f"  {name:<28} A {a:6.2f}  B {b:6.2f}")
    if args.json:
        Path(args.json).write_text(json.dumps({"trees": {k: str(v) for k, v in trees.items()}, "rounds": rounds,
                                               "summary": summary}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
