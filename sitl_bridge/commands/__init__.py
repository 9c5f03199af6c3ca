"""One module per CLI subcommand (`register(subparsers)`), and the options they share."""

from __future__ import annotations

import argparse

from sitl_bridge.autopilot import registry


def add_env_autopilot_argument(parser: argparse.ArgumentParser, default: str = "direct") -> None:
    """`--autopilot`: the env backends, from the autopilot registry (the one list of kinds)."""
    kinds = registry.names(env=True)
    parser.add_argument("--autopilot", choices=kinds, default=default,
                        help="environment backend: " + "; ".join(f"{k}: {registry.get(k).help}" for k in kinds))
