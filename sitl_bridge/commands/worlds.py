"""`sitl-bridge worlds check FILE...`: validate scenario files (world:, task: and train:, and the
geometry's sense), one summary line per file or a one-line error."""

from __future__ import annotations

import argparse
import sys

from sitl_bridge.errors import ConfigError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("worlds", help="validate world/scenario files")
    actions = parser.add_subparsers(dest="worlds_action", metavar="ACTION", required=True)
    check = actions.add_parser("check", help="validate files; one summary line each, exit 1 on any error")
    check.add_argument("files", nargs="+", metavar="FILE", help="scenario YAML files (worlds/*.yaml)")
    check.add_argument("--build", action="store_true",
                       help="also build each world in pybullet (catches unloadable meshes)")
    check.set_defaults(func=check_main)


def check_main(args: argparse.Namespace) -> int:
    """Validate every file; errors are one line each on stderr; exit status 1 if any failed."""
    from sitl_bridge.rl.training.scenario_file import check_scenario_file

    status = 0
    for path in args.files:
        try:
            world = check_scenario_file(path)
            if args.build:
                _build(world)
        except ConfigError as exc:
            print(str(exc), file=sys.stderr)
            status = 1
            continue
        print(f"{path}: ok: {world.summary()}")
    return status


def _build(world) -> None:
    from sitl_bridge.physics import MotorCommand, Simulation

    try:
        with Simulation(world) as sim:
            sim.step([MotorCommand.disarmed()] * sim.num_vehicles)
    except Exception as exc:  # pybullet raises its own error type for unloadable geometry
        raise ConfigError(f"{world.source}: world: cannot be built in pybullet ({exc})") from None
