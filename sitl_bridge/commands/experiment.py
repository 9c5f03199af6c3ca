"""`sitl-bridge experiment EXPERIMENT.yaml --out DIR`: every scenario of the file across its
seeds, and its incremental-complexity comparisons (with vs without the earlier network, same
seeds), trained through the sweep machinery (local processes, or Ray tasks with `--backend ray`);
then each finished run's best checkpoint is evaluated greedily and DIR/RESULTS.md, DIR/results.json
and DIR/figures/ are written. Re-running the same command skips finished runs and resumes
unfinished ones, so an experiment may run in several parts (`--only SCENARIO...` trains some
scenarios; the report always covers every finished run). `--report-only` trains nothing;
`--train-only` writes no report.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import shlex
import sys
from pathlib import Path

from sitl_bridge.errors import ConfigError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("experiment", help="scenarios x seeds + comparisons, resumable, with RESULTS.md",
                                   description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("file", help="experiment file (experiments/*.yaml)")
    parser.add_argument("--out", help="output folder (default runs/experiment__<name>)")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                        help="parallel processes for training and evaluation (local backend; default: CPU count)")
    parser.add_argument("--backend", choices=("local", "ray"), default="local",
                        help="local processes, or Ray tasks (pip install 'sitl-bridge[ray]')")
    parser.add_argument("--address", help="Ray cluster address (default: start Ray's own local cluster; auto: the one 'ray start' runs here)")
    parser.add_argument("--only", nargs="+", metavar="SCENARIO",
                        help="train only these scenarios (file stems; comparisons ending in one of them too)")
    stage = parser.add_mutually_exclusive_group()
    stage.add_argument("--report-only", action="store_true", help="train nothing: evaluate and report the runs there are")
    stage.add_argument("--train-only", action="store_true",
                       help="train (or resume) and stop: leave the report as it is (a part of the runs, "
                            "e.g. with --only, while other parts are still training)")
    parser.add_argument("--eval-episodes", type=int, default=None,
                        help="greedy episodes per run for the reported rates (default: the file's eval_episodes)")
    parser.set_defaults(func=main)


def reproduce_command(args: argparse.Namespace, out: str) -> str:
    """The one command that reproduces every number of the report (no --only: all of it)."""
    argv = ["sitl-bridge", "experiment", args.file, "--out", out]
    if args.eval_episodes is not None:
        argv += ["--eval-episodes", str(args.eval_episodes)]
    return shlex.join(argv)


def main(args: argparse.Namespace) -> int:
    from sitl_bridge.rl.experiments import report, sweep
    from sitl_bridge.rl.experiments import results as res
    from sitl_bridge.rl.experiments import runner as ex

    try:
        if args.workers < 1:
            raise ConfigError(f"command line: --workers: expected an integer >= 1, got {args.workers}")
        if args.eval_episodes is not None and args.eval_episodes < 1:
            raise ConfigError(f"command line: --eval-episodes: expected an integer >= 1, got {args.eval_episodes}")
        experiment = ex.load_experiment(args.file)
        if args.eval_episodes is not None:
            experiment = dataclasses.replace(experiment, eval_episodes=args.eval_episodes)
        ex.selected(experiment, args.only)  # an unknown --only name fails before anything runs
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = args.out or str(Path("runs") / f"experiment__{experiment.name}")

    def say(text: str) -> None:
        print(text, file=sys.stderr, flush=True)

    def on_result(result: sweep.SweepResult) -> None:
        detail = result.error if result.status == "failed" else result.run_dir
        say(f"[{result.status}] {result.point} seed {result.seed}: {detail}")

    failed = False
    if not args.report_only:
        try:
            runs = ex.run_experiment(experiment, out, workers=args.workers, backend=args.backend,
                                     address=args.address, only=args.only, on_result=on_result, say=say)
        except ConfigError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        if runs:
            print(sweep.summary_table(runs))
        failed = any(r.status == "failed" for r in runs)
    if args.train_only:
        return 1 if failed else 0
    results = res.collect(experiment, out, workers=args.workers if args.backend == "local" else 1, say=say)
    report.write_figures(results, out, say=say, settings=experiment.report)
    not_run = res.add_sections(results, out, settings=experiment.report, say=say)
    meta = report.meta_of(experiment, out, reproduce_command(args, out), not_run)
    res.write_json(Path(out) / report.RESULTS_JSON, results)
    res.write_json(Path(out) / report.META_JSON, meta)
    print(f"report: {report.write_report(results, meta, out)}")
    return 1 if failed else 0
