"""`sitl-bridge eval RUN_DIR_OR_CHECKPOINT [--world WORLD.yaml]`: greedy evaluation of a trained
policy, in the run's own scenario unless `--world` names another.

`sitl-bridge eval --rules RULES.yaml [--world WORLD.yaml]`: the same evaluation of a rule set flown
as a scripted controller (`sitl_bridge/rl/analysis/rule_policy.py`), by default in the first scenario it
covers."""

from __future__ import annotations

import argparse
import json
import sys
from typing import TYPE_CHECKING

from sitl_bridge.commands import add_env_autopilot_argument
from sitl_bridge.errors import ConfigError

if TYPE_CHECKING:
    from sitl_bridge.rl.evaluation.evaluate import EvalResult


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("eval", help="greedy evaluation of a checkpoint, run directory or rule set",
                                   description=__doc__)
    parser.add_argument("checkpoint", nargs="?",
                        help="checkpoint file or run directory (newest valid checkpoint); not with --rules")
    parser.add_argument("--rules", metavar="RULES.yaml", help="fly this rule set instead of a checkpoint")
    parser.add_argument("--world", help="scenario file to evaluate in (default: the run's own world; "
                                        "with --rules the first scenario the rules cover)")
    parser.add_argument("--episodes", type=int, default=100, help="evaluation episodes (default 100)")
    add_env_autopilot_argument(parser)
    parser.add_argument("--seed", type=int, default=0, help="seed of the evaluation episodes")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    parser.add_argument("--video", metavar="DIR", help="record each episode as DIR/episode_NNNN.mp4 "
                                                       "(the `video` extra)")
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from sitl_bridge.rl.evaluation.video import VideoUnavailable
    from sitl_bridge.rl.learner.checkpoint import CheckpointError

    if (args.checkpoint is None) == (args.rules is None):
        print("error: give either a checkpoint / run directory or --rules RULES.yaml (exactly one)", file=sys.stderr)
        return 2
    try:
        result = _evaluate_rules(args) if args.rules else _evaluate_checkpoint(args)
    except (ConfigError, CheckpointError, ValueError, VideoUnavailable) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(result.to_dict(), indent=2) if args.json else result.summary())
    return 0


def _evaluate_checkpoint(args: argparse.Namespace) -> EvalResult:
    from sitl_bridge.rl.evaluation.evaluate import evaluate_checkpoint
    from sitl_bridge.rl.training.run_dir import run_scenario

    world = args.world or run_scenario(args.checkpoint)
    result, _ = evaluate_checkpoint(args.checkpoint, world, episodes=args.episodes, autopilot=args.autopilot,
                                    seed=args.seed, progress=True, video_dir=args.video)
    return result


def _evaluate_rules(args: argparse.Namespace) -> EvalResult:
    from sitl_bridge.rl.analysis.rule_policy import covered_scenarios, evaluate_rules, load_rules
    from sitl_bridge.world.lookup import resolve_world

    rules = load_rules(args.rules)
    if args.world:
        world = resolve_world(args.world)
    else:
        covered = covered_scenarios(rules)
        if not covered:
            raise ConfigError(f"{rules.source}: covers: expected a scenario to fly in (or give --world), got []")
        world = covered[0]
    result, _, _ = evaluate_rules(rules, world, episodes=args.episodes, autopilot=args.autopilot, seed=args.seed,
                                  progress=True, video_dir=args.video)
    return result
