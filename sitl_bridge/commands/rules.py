"""`sitl-bridge rules RUN_DIR_OR_CHECKPOINT --world WORLD.yaml`: describe what a trained policy does
(action histograms, typical action sequences, climb-over / sidestep / hover statements) over
randomised greedy episodes: the raw material for the thesis's traffic rules."""

from __future__ import annotations

import argparse
import json
import sys

from sitl_bridge.commands import add_env_autopilot_argument
from sitl_bridge.errors import ConfigError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("rules", help="summarise a trained policy's behaviour (rule extraction)",
                                   description=__doc__)
    parser.add_argument("checkpoint", help="run directory or checkpoint file")
    parser.add_argument("--world", help="scenario file (default: the run's own world)")
    parser.add_argument("--episodes", type=int, default=50, help="randomised greedy episodes (default 50)")
    add_env_autopilot_argument(parser)
    parser.add_argument("--seed", type=int, default=0, help="seed of the episodes")
    parser.add_argument("--top", type=int, default=5, help="typical sequences to list")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from sitl_bridge.rl.checkpoint import CheckpointError
    from sitl_bridge.rl.evaluate import evaluate_checkpoint
    from sitl_bridge.rl.rules import summarize_behaviour
    from sitl_bridge.rl.run_dir import run_scenario

    try:
        world = args.world or run_scenario(args.checkpoint)
        _, traces = evaluate_checkpoint(args.checkpoint, world, episodes=args.episodes,
                                        autopilot=args.autopilot, seed=args.seed, progress=True)
    except (ConfigError, CheckpointError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    summary = summarize_behaviour(str(world), args.episodes, traces, top=args.top)
    print(json.dumps(summary.to_dict(), indent=2) if args.json else summary.report())
    return 0
