"""`sitl-bridge eval CHECKPOINT --world WORLD.yaml`: greedy evaluation of a trained policy."""

from __future__ import annotations

import argparse
import json
import sys

from sitl_bridge.commands import add_env_autopilot_argument
from sitl_bridge.errors import ConfigError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("eval", help="greedy evaluation of a checkpoint or run directory",
                                   description=__doc__)
    parser.add_argument("checkpoint", help="checkpoint file or run directory (newest valid checkpoint)")
    parser.add_argument("--world", required=True, help="scenario file to evaluate in")
    parser.add_argument("--episodes", type=int, default=100, help="evaluation episodes (default 100)")
    add_env_autopilot_argument(parser)
    parser.add_argument("--seed", type=int, default=0, help="seed of the evaluation episodes")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from sitl_bridge.rl.checkpoint import CheckpointError
    from sitl_bridge.rl.evaluate import evaluate_checkpoint

    try:
        result, _ = evaluate_checkpoint(args.checkpoint, args.world, episodes=args.episodes,
                                        autopilot=args.autopilot, seed=args.seed)
    except (ConfigError, CheckpointError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(result.to_dict(), indent=2) if args.json else result.summary())
    return 0
