"""`sitl-bridge plot RUN_DIR`: learning curves (reward, success rate, epsilon, loss) as a PNG."""

from __future__ import annotations

import argparse
import sys


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("plot", help="plot a run's learning curves (PNG)", description=__doc__)
    parser.add_argument("run_dirs", nargs="+", metavar="RUN_DIR", help="run directories")
    parser.add_argument("--out", help="output PNG (one run only; default RUN_DIR/learning_curves.png)")
    parser.add_argument("--window", type=int, default=50, help="episodes in the rolling means (default 50)")
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from sitl_bridge.rl.plots import plot_run

    if args.out and len(args.run_dirs) > 1:
        print("error: --out works with one run directory only", file=sys.stderr)
        return 2
    for run_dir in args.run_dirs:
        try:
            print(plot_run(run_dir, args.out, window=args.window))
        except (OSError, ValueError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    return 0
