"""`sitl-bridge rules RUN_DIR [RUN_DIR ...] [--world WORLD.yaml] [--out RULES.yaml]`: what trained
policies do. Flies each run's greedy policy (the runs are seeds of one scenario) on the same
randomised episodes and prints action histograms and typical sequences, the manoeuvres per seed
(splits when they compete, yields against the priority rule), candidate rules with their
support, and the thesis's rules 0-5 as recovered or not; `--out` writes the rules YAML that
`eval --rules` flies."""

from __future__ import annotations

import argparse
import json
import sys

from sitl_bridge.commands import add_env_autopilot_argument
from sitl_bridge.errors import ConfigError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("rules", help="behaviour of trained policies across seeds, candidate rules",
                                   description=__doc__)
    parser.add_argument("checkpoint", nargs="+", metavar="RUN_DIR",
                        help="run directories (one per seed, same scenario) or checkpoint files")
    parser.add_argument("--world", help="scenario file (default: each run's own world)")
    parser.add_argument("--episodes", type=int, default=50, help="randomised greedy episodes per run (default 50)")
    add_env_autopilot_argument(parser)
    parser.add_argument("--seed", type=int, default=0, help="seed of the episodes")
    parser.add_argument("--top", type=int, default=5, help="typical sequences to list")
    parser.add_argument("--out", metavar="RULES.yaml", help="write the candidate rules as a rules YAML")
    parser.add_argument("--json", action="store_true", help="print everything as JSON")
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from sitl_bridge.rl.analysis.behaviour_runs import analyse_runs
    from sitl_bridge.rl.analysis.candidate_rules import write_rules_yaml
    from sitl_bridge.rl.learner.checkpoint import CheckpointError

    try:
        report = analyse_runs(args.checkpoint, args.world, episodes=args.episodes, seed=args.seed,
                              autopilot=args.autopilot, progress=True, top=args.top)
        if args.out:
            write_rules_yaml(args.out, report.document)
    except (ConfigError, CheckpointError, ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(report.to_dict(), indent=2) if args.json else report.report())
    if args.out and not args.json:
        print(f"rules YAML: {args.out}")
    return 0
