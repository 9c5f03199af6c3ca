"""`sitl-bridge stub -i N`: the PX4-compatible autopilot stub as its own process.

Connects to the simulator's HIL server on TCP 4560+N (retrying, like PX4) and serves PX4's
MAVLink API on UDP 14580+N -> 14540+N (and the GCS link 18570+N -> 14550). When a simulator
session ends the stub restarts fresh, like a new PX4 process, and waits for the next one.
SIGTERM / SIGINT stop it cleanly.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys

from sitl_bridge.errors import ConfigError

log = logging.getLogger(__name__)


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("stub", help="run the PX4-compatible autopilot stub for one vehicle")
    parser.add_argument("-i", "--instance", type=int, default=0,
                        help="vehicle instance N: HIL TCP 4560+N, API UDP 14580+N -> 14540+N (default 0)")
    parser.add_argument("--host", default="127.0.0.1", help="simulator host and API bind address (default 127.0.0.1)")
    parser.add_argument("--ground-truth", action="store_true",
                        help="estimate from HIL_STATE_QUATERNION ground truth instead of the sensors (faster)")
    parser.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                        help="override a parameter (repeatable), e.g. --param MIS_TAKEOFF_ALT=3")
    parser.add_argument("--speed-factor", type=float, default=None,
                        help="scale the `wall` timeouts of px4_params/*.params for this speed factor")
    parser.add_argument("--no-gcs", action="store_true", help="do not serve the GCS link (18570+N -> 14550)")
    parser.add_argument("--once", action="store_true", help="exit when the first simulator session ends")
    parser.set_defaults(func=main)


def parse_param_overrides(items: list[str]) -> dict[str, float]:
    """`NAME=VALUE` strings -> {NAME: value}; a malformed one is a ConfigError."""
    values: dict[str, float] = {}
    for index, item in enumerate(items):
        name, sep, text = item.partition("=")
        try:
            if not sep or not name:
                raise ValueError
            values[name.strip()] = float(text)
        except ValueError:
            raise ConfigError(f"command line: --param[{index}]: expected NAME=VALUE, got {item!r}") from None
    return values


def main(args: argparse.Namespace) -> int:
    from sitl_bridge.autopilot.stub import ParamTable, StubVehicle
    from sitl_bridge.autopilot.stub.params import MAV_PARAM_TYPE_INT32, MAV_PARAM_TYPE_REAL32

    try:
        overrides = parse_param_overrides(args.param)
    except ConfigError as exc:
        print(f"sitl-bridge stub: {exc}", file=sys.stderr)
        return 2
    stopping = False

    def stop(signum: int, _frame: object) -> None:
        nonlocal stopping
        stopping = True

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    while not stopping:
        params = ParamTable(speed_factor=args.speed_factor)
        for name, value in overrides.items():
            if name in params:
                params.set(name, value)
            else:
                params.add(name, value, MAV_PARAM_TYPE_INT32 if value.is_integer() else MAV_PARAM_TYPE_REAL32)
        try:
            vehicle = StubVehicle(args.instance, args.host, ground_truth_estimate=args.ground_truth,
                                  params=params, gcs=not args.no_gcs)
        except OSError as exc:
            log.error("stub %d: cannot open its MAVLink ports (%s); is another autopilot using instance %d?",
                      args.instance, exc.strerror, args.instance)
            return 1
        log.info("stub %d: waiting for the simulator on %s:%d", args.instance, args.host, vehicle.hil.port)
        try:
            vehicle.hil.run(lambda: stopping)
        finally:
            vehicle.close()
        if args.once or vehicle.hil.stats.connections == 0:
            break
        log.info("stub %d: simulator session ended; starting fresh", args.instance)
    return 0
