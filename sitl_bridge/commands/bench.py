"""`sitl-bridge bench`: speed benchmarks. Without a mode flag, every figure in one run
(`sitl_bridge.bench.suite`: `--quick`, `--json FILE`); each mode flag runs one older, more
detailed benchmark module of `sitl_bridge.bench`, which exposes `run(args) -> int`."""

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
    parser.add_argument("--seconds", type=float, default=20.0, help="simulated seconds per case (mode flags)")
    parser.add_argument("--json", metavar="FILE", help="write every figure of the full run to FILE")
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="shorter full run (under 3 minutes)")
    size.add_argument("--smoke", action="store_true", help="seconds-long full run: checks keys, not speed")
    parser.add_argument("--scale", type=float, default=1.0, metavar="X",
                        help="full run: every case runs X times longer (simulated s, episodes, vector steps)")
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    chosen = [name for name in BENCHMARKS if getattr(args, name)]
    if not chosen:
        from sitl_bridge.bench import suite

        return suite.run(args)
    status = 0
    for name in chosen:
        module = importlib.import_module(f"sitl_bridge.bench.{name}")
        status |= module.run(args)
    return status
