"""`sitl-bridge export RUN_DIR [--slim]`: the run's best network alone, as `policy.safetensors`.

The policy file holds the network and what rebuilds it (sizes, dueling head, observation
normaliser statistics), no optimizer, replay or RNG state: tens of KB instead of megabytes. It is
checked on writing against the checkpoint's Q values on fixed probe observations, and on every
read. `eval`, `run --policy`, `transfer`, `rules`, `replay`, `distill` and `train --init-from`
accept it. `--slim` then removes the run's training checkpoints, `best.safetensors` and replay
(a slimmed run can be evaluated and reported, not resumed); nothing is removed before the
export is verified.
"""

from __future__ import annotations

import argparse
import sys


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("export", help="write a run's best network alone as policy.safetensors",
                                   description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dir", metavar="RUN_DIR", help="run directory (or a checkpoint file)")
    parser.add_argument("--out", metavar="FILE", help="where to write (default RUN_DIR/policy.safetensors)")
    parser.add_argument("--slim", action="store_true",
                        help="then remove the run's checkpoints, best.safetensors and replay (no resume after)")
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from sitl_bridge.rl.learner.checkpoint import CheckpointError
    from sitl_bridge.rl.learner.policy_file import PolicyFileError
    from sitl_bridge.rl.training.policy_export import export_policy, slim_run

    try:
        if args.slim:
            if args.out:
                raise CheckpointError("--slim writes RUN_DIR/policy.safetensors; leave --out off")
            export, removed = slim_run(args.run_dir)
        else:
            export, removed = export_policy(args.run_dir, args.out), 0
    except (CheckpointError, PolicyFileError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{export.path}: network of {export.source.name} (episode {export.episode}), {export.bytes} bytes, verified"
          + (f"; removed {removed} bytes of checkpoints and replay" if args.slim else ""))
    return 0
