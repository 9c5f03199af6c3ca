"""`sitl-bridge transfer RUN_DIR... --autopilots direct,stub,px4`: how a trained policy
transfers between backends.

Every run's policy is flown greedily in the run's own scenario on each backend, on the same
evaluation seeds (`rl.evaluation.rollout.eval_seeds`), one env per backend. Per backend: success and
collision (crash) rate of the drone-episodes with Wilson 95 % confidence intervals, and the
mean steps of the successful episodes (a slower velocity response shows there first); where a
backend's rates are more than 10 points from the first backend's, a line on why, from the
episodes (outcome split, steps, distance per step, where the actions part). `--json FILE` also
writes the table. The experiment report's backend table runs the same code (`rl.experiments.backend_transfer`).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from sitl_bridge.autopilot import registry
from sitl_bridge.errors import ConfigError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "transfer", help="evaluate trained policies greedily on several autopilot backends",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", metavar="RUN_DIR", help="training run directories")
    parser.add_argument("--autopilots", default="direct,stub",
                        help="comma-separated env backends (default direct,stub; e.g. direct,stub,px4)")
    parser.add_argument("--episodes", type=int, default=20, help="episodes per backend (default 20)")
    parser.add_argument("--seed", type=int, default=0, help="first evaluation seed (default 0)")
    parser.add_argument("--speed-factor", type=float, default=0.0,
                        help="speed factor of the session backends (default 0: as fast as lockstep allows)")
    parser.add_argument("--instance-base", type=int, default=None,
                        help="preferred first vehicle instance of the session backends (each claims a free "
                             "block from it up, px4 in 0..9; default 100)")
    parser.add_argument("--px4-bin", default=None, help="PX4 SITL binary (default: $PX4_BIN)")
    parser.add_argument("--json", default=None, metavar="FILE", help="also write the table as JSON")
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    autopilots = [a.strip() for a in args.autopilots.split(",") if a.strip()]
    known = registry.names(env=True)
    unknown = [a for a in autopilots if a not in known]
    if unknown or not autopilots:
        print(f"sitl-bridge transfer: --autopilots: expected names from {', '.join(known)}, "
              f"got {args.autopilots!r}", file=sys.stderr)
        return 2
    if args.episodes < 1:
        print("sitl-bridge transfer: --episodes must be at least 1", file=sys.stderr)
        return 2
    # torch and mavsdk are only imported for this command
    from sitl_bridge.rl.experiments.backend_transfer import (
        differs,
        fly_on_backend,
        same_actions,
        summary,
        why_differ,
    )
    from sitl_bridge.rl.learner.policy import policy_from_checkpoint
    from sitl_bridge.rl.training.run_dir import run_dir_of, run_scenario

    rows = []
    try:
        for run in args.runs:
            if not run_dir_of(run):
                raise ConfigError(f"{run}: not a training run directory (no run.json)")
            world = str(run_scenario(run))
            policy = policy_from_checkpoint(run)
            reference = None  # the first backend: the others are compared with it
            for autopilot in autopilots:
                flight = fly_on_backend(policy, world, autopilot, episodes=args.episodes, seed=args.seed,
                                        speed_factor=args.speed_factor, instance_base=args.instance_base,
                                        px4_bin=args.px4_bin)
                row = {"run": str(run), "world": Path(world).name, "autopilot": autopilot, **summary(flight)}
                if reference is None:
                    reference = flight
                else:
                    row["same_actions_as"] = {"autopilot": reference.autopilot, **same_actions(reference, flight)}
                    if differs(summary(reference), row):
                        row["why"] = why_differ(reference.autopilot, reference, flight)
                rows.append(row)
                print(_format(row), flush=True)
                if row.get("why"):
                    print(f"  why: {row['why']}", flush=True)
    except KeyboardInterrupt:
        print("\ninterrupted", file=sys.stderr)
        return 130
    except (ConfigError, ValueError, FileNotFoundError) as exc:
        print(f"sitl-bridge transfer: {exc}", file=sys.stderr)
        return 2
    except RuntimeError as exc:  # a backend that could not start (no PX4 build, busy ports)
        print(f"sitl-bridge transfer: {exc}", file=sys.stderr)
        return 1
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2) + "\n")
    return 0


def _format(row: dict) -> str:
    s_lo, s_hi = row["success_ci95"]
    c_lo, c_hi = row["collision_ci95"]
    steps, same = row["mean_steps_success"], row.get("same_actions_as")
    return (f"{row['run']} ({row['world']}) {row['autopilot']:>8}: success {row['success']:4.0%} "
            f"[{s_lo:.0%}, {s_hi:.0%}], collision {row['collision']:4.0%} [{c_lo:.0%}, {c_hi:.0%}], "
            f"steps to goal {'-' if steps is None else f'{steps:.1f}'} ({row['drone_episodes']} drone-episodes)"
            + (f", same actions as {same['autopilot']} in {same['identical']}/{same['compared']}" if same else ""))
