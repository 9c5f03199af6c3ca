"""`sitl-bridge stub -i N`: the PX4-compatible autopilot stub as its own process.

Connects to the simulator's HIL server on TCP 4560+N (retrying, like PX4) and serves PX4's
MAVLink API on UDP 14580+N -> 14540+N (and the GCS link 18570+N -> 14550). When the simulator
session ends (the simulator closed the link or died) the stub exits, as PX4 does; with
`--keep-alive` it restarts fresh, like a new PX4 process, and waits for the next session.
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
    parser.add_argument("--fence", default=None, metavar="LAT,LON,ALT,MIN_X,MIN_Y,MIN_Z,MAX_X,MAX_Y,MAX_Z",
                        help="refuse position commands outside this box (world ENU metres around the "
                             "geodetic origin LAT,LON,ALT); the session's stub-process kind passes its world's workspace")
    parser.add_argument("--no-gcs", action="store_true", help="do not serve the GCS link (18570+N -> 14550)")
    parser.add_argument("--keep-alive", action="store_true",
                        help="after a simulator session ends, start fresh and wait for the next one")
    parser.add_argument("--once", action="store_true", help=argparse.SUPPRESS)  # the default now
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
    from sitl_bridge.autopilot.stub.fence import Fence
    from sitl_bridge.autopilot.stub.params import MAV_PARAM_TYPE_INT32, MAV_PARAM_TYPE_REAL32
    from sitl_bridge.ports import vehicle_ports

    try:
        overrides = parse_param_overrides(args.param)
        fence = Fence.from_text(args.fence) if args.fence is not None else None
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
                                  params=params, gcs=not args.no_gcs, fence=fence)
        except OSError as exc:
            log.error("stub %d: cannot open its MAVLink ports (%s); is another autopilot using instance %d? Pick another with -i",
                      args.instance, exc.strerror, args.instance)
            return 1
        ports = vehicle_ports(args.instance)
        print(f"sitl-bridge stub {args.instance}: waiting for the simulator on tcp {args.host}:{ports.hil}; "
              f"MAVLink API udp {ports.api_bind} -> {ports.api_client}"
              + ("" if args.no_gcs else f", GCS udp {ports.gcs_bind} -> {ports.gcs_remote}")
              + " (Ctrl-C stops)", flush=True)
        try:
            vehicle.hil.run(lambda: stopping)
        finally:
            vehicle.close()
        if stopping or vehicle.hil.stats.connections == 0:
            break
        if not args.keep_alive:
            print(f"sitl-bridge stub {args.instance}: the simulator closed the link; exiting "
                  "(--keep-alive waits for the next session)", flush=True)
            break
        print(f"sitl-bridge stub {args.instance}: simulator session ended; starting fresh", flush=True)
    return 0
