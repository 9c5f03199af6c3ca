"""`sitl-bridge eval RUN_DIR_OR_CHECKPOINT [--world WORLD.yaml]`: greedy evaluation of a trained
policy, in the run's own scenario unless `--world` names another.

`sitl-bridge eval --rules RULES.yaml [--world WORLD.yaml]`: the same evaluation of a rule set flown
as a scripted controller (`sitl_bridge/rl/analysis/rule_policy.py`), by default in the first scenario it
covers.

`sitl-bridge eval --policy orca --world WORLD.yaml`: the classical baseline, every drone flying the
velocity ORCA picks from its own observation (`sitl_bridge/rl/analysis/orca_policy.py`).

Episodes (reset seeds `eval_seeds(S, n)`, `sitl_bridge/rl/experiments/seeds.py`): by default a
checkpoint flies the report's held-out evaluation set of its run (S = 1000000 + the run's seed),
not the periodic evaluations that chose its best checkpoint (S = the run's seed); a rule set flies
the verification set (S = 3000000), none of the episodes rules are mined on; ORCA the evaluation
set of seed 0 (S = 1000000). `--seed S` picks another set. With several drones the loss of
separation (closer than 1 m) is printed too."""

from __future__ import annotations

import argparse
import json
import sys
from typing import TYPE_CHECKING

from sitl_bridge.commands import add_env_autopilot_argument
from sitl_bridge.errors import ConfigError

if TYPE_CHECKING:
    from sitl_bridge.rl.evaluation.evaluate import EvalResult
    from sitl_bridge.rl.evaluation.rollout import Trace


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("eval", help="greedy evaluation of a checkpoint, run directory or rule set",
                                   description=__doc__)
    parser.add_argument("checkpoint", nargs="?",
                        help="checkpoint file, or run directory: its best checkpoint (best.safetensors; without "
                             "one its policy export, else its newest valid checkpoint)")
    parser.add_argument("--rules", metavar="RULES.yaml", help="fly this rule set instead of a checkpoint")
    parser.add_argument("--policy", choices=("orca",), help="fly a classical policy instead (needs --world)")
    parser.add_argument("--world", help="scenario file to evaluate in (default: the run's own world; "
                                        "with --rules the first scenario the rules cover)")
    parser.add_argument("--episodes", type=int, default=100, help="evaluation episodes (default 100)")
    add_env_autopilot_argument(parser)
    parser.add_argument("--seed", type=int, default=None,
                        help="episode set: reset seeds eval_seeds(SEED, n) (default: a held-out set, see above)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    parser.add_argument("--video", metavar="DIR", help="record each episode as DIR/episode_NNNN.mp4 "
                                                       "(the `video` extra)")
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from sitl_bridge.rl.evaluation.separation import separation
    from sitl_bridge.rl.evaluation.video import VideoUnavailable
    from sitl_bridge.rl.learner.checkpoint import CheckpointError

    if sum(x is not None for x in (args.checkpoint, args.rules, args.policy)) != 1:
        print("error: give a checkpoint / run directory, --rules RULES.yaml or --policy orca (exactly one)",
              file=sys.stderr)
        return 2
    if args.policy and not args.world:
        print(f"error: --policy {args.policy} needs --world WORLD.yaml (the scenario to fly in)", file=sys.stderr)
        return 2
    evaluate = _evaluate_rules if args.rules else _evaluate_policy if args.policy else _evaluate_checkpoint
    try:
        result, traces = evaluate(args)
    except (ConfigError, CheckpointError, ValueError, VideoUnavailable) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    apart = separation(traces)
    print(args.episode_set, file=sys.stderr)
    if args.json:
        print(json.dumps({**result.to_dict(), "episode_seed": args.seed, "separation": apart.to_dict()}, indent=2))
    else:
        print(result.summary() + (f"; {apart.summary()}" if apart.episodes else ""))
    return 0


def _episode_set(args: argparse.Namespace, base: int, what: str, run_seed: int = 0) -> None:
    """Set `args.seed` to the default set unless given, and `args.episode_set` to the line that
    says which set flew (printed on stderr after the result: a bad input stays one line)."""
    from sitl_bridge.rl.experiments.seeds import seed_set

    given = args.seed is not None
    if not given:
        args.seed = seed_set(base, run_seed)
    args.episode_set = (f"episodes: reset seeds eval_seeds({args.seed}, {args.episodes}), "
                        + ("given by --seed" if given else what))


def _run_seed(checkpoint: str) -> int | None:
    """The seed of the run holding `checkpoint` (None: not inside a run directory)."""
    from sitl_bridge.rl.training.run_dir import read_run_files, run_dir_of

    run_dir = run_dir_of(checkpoint)
    return None if run_dir is None else read_run_files(run_dir)[0].seed


def _evaluate_checkpoint(args: argparse.Namespace) -> tuple[EvalResult, list[Trace]]:
    from sitl_bridge.rl.evaluation.evaluate import evaluate_checkpoint
    from sitl_bridge.rl.experiments.seeds import EVAL_SEED_BASE
    from sitl_bridge.rl.training.run_dir import run_scenario

    world = args.world or run_scenario(args.checkpoint)
    run_seed = _run_seed(args.checkpoint)
    _episode_set(args, EVAL_SEED_BASE, "the held-out evaluation set " + (
        f"of run seed {run_seed} (the report's; not the episodes that chose its best checkpoint)"
        if run_seed is not None else "of seed 0 (not inside a run directory)"), run_seed or 0)
    return evaluate_checkpoint(args.checkpoint, world, episodes=args.episodes, autopilot=args.autopilot,
                               seed=args.seed, progress=True, video_dir=args.video)


def _evaluate_policy(args: argparse.Namespace) -> tuple[EvalResult, list[Trace]]:
    from sitl_bridge.rl.analysis.orca_policy import orca_policy
    from sitl_bridge.rl.evaluation.evaluate import evaluate_in_world
    from sitl_bridge.rl.experiments.seeds import EVAL_SEED_BASE
    from sitl_bridge.world.lookup import resolve_world

    world = resolve_world(args.world)
    _episode_set(args, EVAL_SEED_BASE, "the held-out evaluation set of seed 0")
    return evaluate_in_world(orca_policy(world), world, episodes=args.episodes, autopilot=args.autopilot,
                             seed=args.seed, progress=True, video_dir=args.video)


def _evaluate_rules(args: argparse.Namespace) -> tuple[EvalResult, list[Trace]]:
    from sitl_bridge.rl.analysis.rule_policy import covered_scenarios, evaluate_rules, load_rules
    from sitl_bridge.rl.experiments.seeds import VERIFY_SEED_BASE
    from sitl_bridge.world.lookup import resolve_world

    rules = load_rules(args.rules)
    if args.world:
        world = resolve_world(args.world)
    else:
        covered = covered_scenarios(rules)
        if not covered:
            raise ConfigError(f"{rules.source}: covers: expected a scenario to fly in (or give --world), got []")
        world = covered[0]
    _episode_set(args, VERIFY_SEED_BASE, "the verification set (none of the episodes rules are mined on)")
    result, traces, _ = evaluate_rules(rules, world, episodes=args.episodes, autopilot=args.autopilot, seed=args.seed,
                                       progress=True, video_dir=args.video)
    return result, traces
