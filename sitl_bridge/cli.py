"""The `sitl-bridge` command line.

Each subcommand lives in its own module under `sitl_bridge.commands` and exposes
`register(subparsers)`, which adds its parser and sets `func` (called with the parsed args,
returning an exit code). This file only wires them together.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import logging
import sys

from sitl_bridge import __version__
from sitl_bridge.errors import ConfigError

# Order here is the order in `--help`.
COMMAND_MODULES = (
    "run",
    "stub",
    "worlds",
    "bench",
    "train",
    "sweep",
    "eval",
    "eval_encounters",
    "transfer",
    "lr_probe",
    "curriculum",
    "experiment",
    "plot",
    "rules",
    "distill",
    "replay",
    "export",
)


def build_parser() -> argparse.ArgumentParser:
    """Build the top-level parser with every available subcommand."""
    parser = argparse.ArgumentParser(
        prog="sitl-bridge",
        description="Lockstep drone simulator, PX4-compatible autopilot stub, RL environments.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-vv: debug)")
    parser.add_argument("--version", action="version", version=f"sitl-bridge {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        module_name = f"sitl_bridge.commands.{name}"
        if importlib.util.find_spec(module_name) is None:
            continue
        try:
            module = importlib.import_module(module_name)
        except Exception as exc:  # one broken command must not take the others down
            _register_broken(subparsers, name, exc)
            continue
        module.register(subparsers)
    return parser


def _register_broken(subparsers: argparse._SubParsersAction, name: str, exc: Exception) -> None:
    """A placeholder subcommand that reports why the real one could not be loaded."""
    command = name.replace("_", "-")
    parser = subparsers.add_parser(command, help=f"(unavailable: {exc})", add_help=False)
    parser.add_argument("rest", nargs=argparse.REMAINDER)

    def fail(_args: argparse.Namespace) -> int:
        print(f"sitl-bridge {command}: cannot load this command: {exc!r}", file=sys.stderr)
        return 1

    parser.set_defaults(func=fail)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `sitl-bridge` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except ConfigError as exc:  # a bad file is the user's to fix: one line, no traceback
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
