"""`sitl-bridge lr-probe WORLD.yaml`: the thesis's learning-rate probe. Collect the first batches
with a random policy, train many epochs on them at decreasing rates, report the highest rate whose
loss does not diverge (a safe starting `learning_rate` for the scenario's `train:` section)."""

from __future__ import annotations

import argparse
import json
import sys

from sitl_bridge.commands import add_env_autopilot_argument
from sitl_bridge.errors import ConfigError
from sitl_bridge.rl.learner.config import (
    add_config_arguments,
    load_train_config,
    overrides_from_args,
)


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("lr-probe", help="find a safe starting learning rate (thesis procedure)",
                                   description=__doc__)
    parser.add_argument("world", help="scenario file")
    add_env_autopilot_argument(parser)
    parser.add_argument("--batches", type=int, default=5, help="batches of random experience to collect")
    parser.add_argument("--epochs", type=int, default=100, help="training epochs per rate")
    parser.add_argument("--rates", type=float, nargs="+", help="candidate rates (default 0.1 ... 1e-7)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    add_config_arguments(parser)
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from sitl_bridge.rl.common.drones_env import scenario_env_factory
    from sitl_bridge.rl.training.lr_probe import DEFAULT_RATES, probe

    try:
        config = load_train_config(args.world, overrides_from_args(args))
        if config.algorithm != "dqn":
            raise ConfigError(f"lr-probe probes DQN's learning rate only (this config trains {config.algorithm}; "
                              f"give --algorithm dqn, or tune learning_rate in its train.{config.algorithm} mapping)")
        result = probe(scenario_env_factory(args.world, args.autopilot), config, batches=args.batches,
                       epochs=args.epochs, rates=tuple(args.rates or DEFAULT_RATES), seed=args.seed)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(result.to_dict(), indent=2) if args.json else result.report())
    return 0 if result.safe_learning_rate is not None else 1
