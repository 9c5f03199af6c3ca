"""`sitl-bridge bench`: speed benchmarks. Each flag runs one benchmark module of
`sitl_bridge.bench`, which exposes `run(args) -> int` and prints its figures."""

from __future__ import annotations

import argparse
import importlib

BENCHMARKS = {
    "physics": "physics and sensors alone (1 and 2 vehicles, with lidar)",
    "link": "lockstep HIL link with a trivial autopilot peer",
    "stub": "full protocol path: simulator + HIL link + stub autopilot",
    "env": "environment steps per backend (direct, stub)",
}


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("bench", help="run speed benchmarks")
    for name, text in BENCHMARKS.items():
        parser.add_argument(f"--{name}", action="store_true", help=text)
    parser.add_argument("--seconds", type=float, default=20.0, help="simulated seconds per case")
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    chosen = [name for name in BENCHMARKS if getattr(args, name)] or list(BENCHMARKS)
    status = 0
    for name in chosen:
        module = importlib.import_module(f"sitl_bridge.bench.{name}")
        status |= module.run(args)
    return status
