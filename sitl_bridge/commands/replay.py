"""`sitl-bridge replay RUN_DIR --episode N --out FILE.png|.gif`: a picture of one episode, a top
view above a side view of the world (obstacles, goals, workspace, movers) with every drone's path
and its action codes along it; `.gif` animates it step by step.

By default episode N is training episode N of the run's log (`episodes.jsonl`), flown again from
its reset seed with its logged actions in the run's own scenario (a warning says so if the
re-flight differs from the log). `--greedy` flies the run's greedy policy (newest valid
checkpoint) in evaluation episode N of `sitl-bridge eval --seed S` instead."""

from __future__ import annotations

import argparse
import sys

from sitl_bridge.commands import add_env_autopilot_argument
from sitl_bridge.errors import ConfigError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("replay", help="picture (PNG) or animation (GIF) of one episode",
                                   description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", metavar="RUN_DIR", help="run directory (or, with --greedy, a checkpoint file)")
    parser.add_argument("--episode", type=int, required=True, metavar="N",
                        help="training episode N of the log (with --greedy: evaluation episode N)")
    parser.add_argument("--out", required=True, metavar="FILE", help="FILE.png (still) or FILE.gif (animation)")
    parser.add_argument("--greedy", action="store_true",
                        help="fly the run's greedy policy instead of the logged actions")
    parser.add_argument("--seed", type=int, default=0,
                        help="with --greedy: seed of the evaluation episodes, as `eval --seed` (default 0)")
    parser.add_argument("--fps", type=float, default=4.0, help="GIF frames (action steps) per second (default 4)")
    add_env_autopilot_argument(parser)
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from pathlib import Path

    from sitl_bridge.rl.analysis.pictures import FORMATS, draw_episode
    from sitl_bridge.rl.analysis.reflight import greedy_pictures, refly_logged
    from sitl_bridge.rl.learner.checkpoint import CheckpointError

    out = Path(args.out)
    try:
        if out.suffix.lower() not in FORMATS:
            raise ValueError(f"--out {out}: expected a .png or .gif file name")
        if args.episode < 0:
            raise ValueError(f"--episode: episode numbers start at 0, got {args.episode}")
        if args.fps <= 0:
            raise ValueError(f"--fps: expected a positive number, got {args.fps:g}")
        if args.greedy:
            (picture,) = greedy_pictures(args.run, [args.episode], seed=args.seed, autopilot=args.autopilot)
        else:
            picture, differences = refly_logged(args.run, args.episode, autopilot=args.autopilot)
            if differences:
                print(f"warning: the re-flown episode {args.episode} differs from the log "
                      f"({'; '.join(differences)}); the picture shows the re-flight", file=sys.stderr)
        out.parent.mkdir(parents=True, exist_ok=True)
        draw_episode(picture.scenario, picture.layout, picture.traces, out, movers=picture.movers,
                     title=picture.title, fps=args.fps)
    except (ConfigError, CheckpointError, ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {out}")
    return 0
