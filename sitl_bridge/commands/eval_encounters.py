"""`sitl-bridge eval-encounters --world WORLD.yaml --per-type N [--orca] [--rules R.yaml]...
[--checkpoint RUN]...`: every named policy flies N episodes of each encounter type of the world
(a `world.encounter` family; several `--world`s: one after the other), the same episodes for
every policy, and the table per type and policy is printed in markdown: success, collision and
loss-of-separation (< 1 m) rates per episode with Wilson 95 % intervals, time to goal and path
length (`sitl_bridge/rl/evaluation/encounter_table.py`).

Episodes: reset seeds `eval_seeds(S, ...)` of a named set (`sitl_bridge/rl/experiments/seeds.py`):
by default the verification set (S = 3000000; no rule is mined and no checkpoint chosen on it),
`--episode-set evaluation` the report's evaluation set of seed 0 (S = 1000000); `--seed S` any.
`--json PATH` writes the rows and every episode's record."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

from sitl_bridge.commands import add_env_autopilot_argument
from sitl_bridge.errors import ConfigError

EPISODE_SETS = ("verification", "evaluation")


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("eval-encounters", help="per-encounter-type table of policies on an encounter family",
                                   description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--world", action="append", required=True, help="encounter scenario file (repeatable)")
    parser.add_argument("--per-type", type=int, default=50, help="episodes per encounter type (default 50)")
    parser.add_argument("--orca", action="store_true", help="fly the ORCA baseline")
    parser.add_argument("--rules", action="append", default=[], metavar="RULES.yaml", help="fly a rule set (repeatable)")
    parser.add_argument("--checkpoint", action="append", default=[], metavar="RUN_OR_CHECKPOINT",
                        help="fly a trained policy: a checkpoint file or run directory (repeatable)")
    parser.add_argument("--episode-set", choices=EPISODE_SETS, default="verification",
                        help="named set of reset seeds (default verification)")
    parser.add_argument("--seed", type=int, default=None, help="eval_seeds(SEED, ...) instead of a named set")
    add_env_autopilot_argument(parser)
    parser.add_argument("--json", metavar="PATH", help="write the rows and per-episode records as JSON")
    parser.set_defaults(func=main)


def _policies(args: argparse.Namespace, world: Path) -> list[tuple[str, Callable[[np.ndarray], int]]]:
    from sitl_bridge.rl.analysis.orca_policy import orca_policy
    from sitl_bridge.rl.analysis.rule_policy import load_rules, rule_policy
    from sitl_bridge.rl.learner.policy import policy_from_checkpoint

    chosen: list[tuple[str, Callable[[np.ndarray], int]]] = []
    for checkpoint in args.checkpoint:
        chosen.append((f"learned {checkpoint}", policy_from_checkpoint(checkpoint)))
    for path in args.rules:
        rules = load_rules(path)
        chosen.append((f"rules: {rules.name}", rule_policy(rules, world)))
    if args.orca:
        chosen.append(("ORCA", orca_policy(world)))
    return chosen


def main(args: argparse.Namespace) -> int:
    from sitl_bridge.envs.scenario import load_scenario
    from sitl_bridge.rl.common.drones_env import DronesEnv, scenario_env_factory
    from sitl_bridge.rl.evaluation.encounter_table import (
        by_type,
        encounter_labels,
        fly_per_type,
        markdown_table,
    )
    from sitl_bridge.rl.experiments.seeds import SEED_BASES, seed_set
    from sitl_bridge.rl.learner.checkpoint import CheckpointError
    from sitl_bridge.world.lookup import resolve_world

    if not (args.orca or args.rules or args.checkpoint):
        print("error: name at least one policy: --orca, --rules RULES.yaml or --checkpoint RUN", file=sys.stderr)
        return 2
    if args.per_type < 1:
        print(f"error: --per-type: expected at least 1, got {args.per_type}", file=sys.stderr)
        return 2
    seed = args.seed if args.seed is not None else seed_set(SEED_BASES[args.episode_set])
    which = f"--seed {seed}" if args.seed is not None else f"the {args.episode_set} set"
    records = []
    try:
        for name in args.world:
            world = resolve_world(name)
            scenario = load_scenario(world)
            labels = encounter_labels(scenario.world)
            policies = _policies(args, world)
            env = DronesEnv(scenario_env_factory(world, args.autopilot)(seed))
            try:
                for policy_name, policy in policies:
                    records += fly_per_type(env, policy, policy_name=policy_name, world=world.stem, labels=labels,
                                            per_type=args.per_type, seed=seed,
                                            action_duration_s=scenario.task.action.duration_s, progress=True)
            finally:
                env.close()
    except (ConfigError, CheckpointError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    rows = by_type(records)
    print(f"episodes: reset seeds eval_seeds({seed}, ...), {which}; {args.per_type} per encounter type",
          file=sys.stderr)
    print(markdown_table(rows))
    if args.json:
        Path(args.json).write_text(json.dumps({
            "seed": seed, "episode_set": None if args.seed is not None else args.episode_set,
            "per_type": args.per_type, "rows": [r.to_dict() for r in rows],
            "episodes": [r.to_dict() for r in records]}, indent=1) + "\n")
    return 0
