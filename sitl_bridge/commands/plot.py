"""`sitl-bridge plot RUN_DIR [RUN_DIR ...]`: the learning-curve figure (PNG).

One run: its greedy success during training, outcome shares, reward per term, epsilon and loss.
Several runs (e.g. the seeds of one scenario): one figure with their mean and 95 % band.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("plot", help="plot learning curves of one run or of several seeds (PNG)",
                                   description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dirs", nargs="+", metavar="RUN_DIR", help="run directories")
    parser.add_argument("--out", help="output PNG (default: RUN_DIR/learning_curves.png for one run, "
                                      "learning_curves.png in the runs' common folder for several)")
    parser.add_argument("--window", type=int, default=50,
                        help="episodes in the rolling means (default 50, at most the run's length)")
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from sitl_bridge.rl.analysis.plots import NotARun, plot_runs

    out = args.out
    if out is None and len(args.run_dirs) > 1:
        common = Path(os.path.commonpath([str(Path(d).resolve()) for d in args.run_dirs]))
        out = common / "learning_curves.png"
    try:
        print(plot_runs(args.run_dirs, out, window=max(1, args.window)))
    except NotARun as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"error: {exc.filename or ''}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    return 0
