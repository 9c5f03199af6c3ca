"""`sitl-bridge eval RUN_DIR_OR_CHECKPOINT [--world WORLD.yaml]`: greedy evaluation of a trained
policy, in the run's own scenario unless `--world` names another."""

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
    parser.add_argument("--world", help="scenario file to evaluate in (default: the run's own world)")
    parser.add_argument("--episodes", type=int, default=100, help="evaluation episodes (default 100)")
    add_env_autopilot_argument(parser)
    parser.add_argument("--seed", type=int, default=0, help="seed of the evaluation episodes")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    parser.add_argument("--video", metavar="DIR", help="record each episode as DIR/episode_NNNN.mp4 "
                                                       "(the `video` extra)")
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from sitl_bridge.rl.checkpoint import CheckpointError
    from sitl_bridge.rl.evaluate import evaluate_checkpoint
    from sitl_bridge.rl.run_dir import run_scenario
    from sitl_bridge.rl.video import VideoUnavailable

    try:
        world = args.world or run_scenario(args.checkpoint)
        result, _ = evaluate_checkpoint(args.checkpoint, world, episodes=args.episodes,
                                        autopilot=args.autopilot, seed=args.seed, progress=True,
                                        video_dir=args.video)
    except (ConfigError, CheckpointError, ValueError, VideoUnavailable) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(result.to_dict(), indent=2) if args.json else result.summary())
    return 0
