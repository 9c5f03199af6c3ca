"""`sitl-bridge curriculum FILE.yaml`: incremental complexity. Train the file's stages in order
(e.g. ER -> TE), each from the previous stage's network, and re-evaluate every new policy in the
earlier stages' scenarios. Re-running the same command resumes an interrupted curriculum."""

from __future__ import annotations

import argparse
import sys

from sitl_bridge.commands import add_env_autopilot_argument
from sitl_bridge.errors import ConfigError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("curriculum", help="train scenarios in order, each from the previous one",
                                   description=__doc__)
    parser.add_argument("file", help="curriculum file (worlds/curricula/*.yaml)")
    parser.add_argument("--out", default="runs", help="output folder (default runs/)")
    parser.add_argument("--seed", type=int, default=0)
    add_env_autopilot_argument(parser)
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from sitl_bridge.rl.learner.checkpoint import CheckpointError
    from sitl_bridge.rl.training.curriculum import load_curriculum, run_curriculum
    from sitl_bridge.rl.training.init_from import ShapeMismatch

    try:
        curriculum = load_curriculum(args.file)
        run_curriculum(curriculum, args.out, seed=args.seed, autopilot=args.autopilot,
                       progress=not args.no_progress)
    except (ConfigError, CheckpointError, ShapeMismatch) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0
