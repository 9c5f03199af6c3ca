"""`sitl-bridge sweep WORLD.yaml --seeds 0-9 [--grid GRID.yaml] [--workers K]`: independent
training runs in parallel processes (or Ray tasks with `--backend ray`), each with its own run
directory and vehicle instances; a summary table at the end. Re-running the same command skips
finished runs and resumes unfinished ones. GRID.yaml maps hyperparameters to lists of values
(`learning_rate: [0.001, 0.0001]`); every combination runs for every seed. Hyperparameter
options (`--episodes 50`, ...) apply to every run.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from sitl_bridge.errors import ConfigError
from sitl_bridge.rl.learner.config import add_config_arguments, overrides_from_args


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("sweep", help="many training runs (seeds x grid) in parallel, resumable",
                                   description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("world", help="scenario file (worlds/*.yaml)")
    parser.add_argument("--seeds", default="0-9", help="seeds: 0-9, 3 or 0,2,5-7 (default 0-9)")
    parser.add_argument("--grid", metavar="GRID.yaml", help="hyperparameter grid: {name: [values]}")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                        help="parallel processes (local backend; default: CPU count)")
    parser.add_argument("--backend", choices=("local", "ray"), default="local",
                        help="local processes, or Ray tasks (pip install 'sitl-bridge[ray]')")
    parser.add_argument("--address", help="Ray cluster address (default: start Ray's own local cluster; auto: the one 'ray start' runs here)")
    parser.add_argument("--autopilot", choices=("direct", "stub", "px4"), default="direct")
    parser.add_argument("--instance-base", type=int, default=0,
                        help="preferred first vehicle instance (stub/px4 ports 4560+i, ...); each run "
                             "claims a free block from it up")
    parser.add_argument("--out", help="sweep root (default runs/sweep__<world>)")
    parser.add_argument("--watchdog", action="store_true",
                        help="supervise every run like `train --watchdog` (direct backend): a run that dies "
                             "or freezes restarts from its last checkpoint")
    add_config_arguments(parser)
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from sitl_bridge.rl.experiments import sweep

    try:
        if args.workers < 1:
            raise ConfigError(f"command line: --workers: expected an integer >= 1, got {args.workers}")
        if not Path(args.world).is_file():
            raise ConfigError(f"command line: WORLD: expected a scenario file, got {args.world!r}")
        if args.watchdog and args.autopilot != "direct":
            raise ConfigError("command line: --watchdog: supervised sweeps run the direct backend only, "
                              f"got --autopilot {args.autopilot}")
        seeds = sweep.parse_seeds(args.seeds)
        points = sweep.load_grid(args.grid, args.world)
        common = {k: v for k, v in overrides_from_args(args).items() if v is not None}
        # absolute paths: Ray runs tasks in other working directories (and on other nodes)
        root = str(Path(args.out or Path("runs") / f"sweep__{Path(args.world).stem}").resolve())
        jobs = sweep.plan(str(Path(args.world).resolve()), seeds, points, root, autopilot=args.autopilot,
                          instance_base=args.instance_base, common=common, watchdog=args.watchdog)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2

    def report(result: sweep.SweepResult) -> None:
        detail = result.error if result.status == "failed" else result.run_dir
        print(f"[{result.status}] {result.point} seed {result.seed}: {detail}", file=sys.stderr, flush=True)

    print(f"sweep: {len(jobs)} runs ({len(points)} grid points x {len(seeds)} seeds) under {root}, "
          f"backend {args.backend}", file=sys.stderr)
    try:
        if args.backend == "ray":
            results = sweep.run_ray(jobs, args.address, on_result=report)
        else:
            results = sweep.run_local(jobs, args.workers, on_result=report)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    path = sweep.write_summary(root, results)
    print(sweep.summary_table(results))
    print(f"summary: {path}")
    return 1 if any(r.status == "failed" for r in results) else 0
