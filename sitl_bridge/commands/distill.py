"""`sitl-bridge distill RUN_DIR`: fit a shallow decision tree that flies like the run's greedy
network (VIPER-weighted, DAgger resampling), report its depth, fidelity to the network and its
success and return next to the network's on the same evaluation episodes, and print it as
if-then text; `--rules-out` writes it as a rules YAML that `eval --rules` flies."""

from __future__ import annotations

import argparse
import json
import sys

from sitl_bridge.commands import add_env_autopilot_argument
from sitl_bridge.errors import ConfigError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("distill", help="distil a trained policy into a readable decision tree",
                                   description=__doc__)
    parser.add_argument("run_dir", help="run directory or checkpoint file")
    parser.add_argument("--world", help="scenario file (default: the run's own world)")
    parser.add_argument("--max-depth", type=int, default=6, help="deepest tree allowed (default 6)")
    parser.add_argument("--iterations", type=int, default=5,
                        help="DAgger iterations = trees fitted and scored (default 5)")
    parser.add_argument("--episodes", type=int, default=20,
                        help="episodes per iteration and for the final comparison (default 20)")
    add_env_autopilot_argument(parser)
    parser.add_argument("--seed", type=int, default=0, help="seed of the episodes (evaluation: as `eval --seed`)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    parser.add_argument("--rules-out", metavar="RULES.yaml", help="write the tree as a rules YAML")
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from sitl_bridge.rl.analysis.distill import Candidate, distill_run
    from sitl_bridge.rl.common.atomic import atomic_write_text
    from sitl_bridge.rl.learner.checkpoint import CheckpointError

    if args.max_depth < 1 or args.iterations < 1 or args.episodes < 1:
        print("error: --max-depth, --iterations and --episodes must be at least 1", file=sys.stderr)
        return 2

    def report(candidate: Candidate) -> None:
        print(f"iteration {candidate.iteration}: depth {candidate.depth}, {candidate.leaves} leaves, "
              f"{candidate.samples} states; held-out fidelity {candidate.fidelity:.1%}, "
              f"success {candidate.success:.0%}", file=sys.stderr)

    try:
        result = distill_run(args.run_dir, world=args.world, max_depth=args.max_depth,
                             iterations=args.iterations, episodes=args.episodes, seed=args.seed,
                             autopilot=args.autopilot, on_candidate=report)
        if args.rules_out:
            atomic_write_text(args.rules_out, result.rules_yaml())
    except (ConfigError, CheckpointError, ValueError, RuntimeError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(result.to_dict(), indent=2) if args.json else result.summary())
    if args.rules_out and not args.json:
        print(f"\nrules written to {args.rules_out}")
    return 0
