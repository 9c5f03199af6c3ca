"""`sitl-bridge run`: the simulator, one autopilot per vehicle, the MAVLink API for clients.

Serves PX4's MAVLink API on UDP 14580+i -> 14540+i per vehicle (MAVSDK, QGroundControl,
MAVProxy connect as they would to PX4 SITL), prints a live status line, and with `--demo`
flies the built-in MAVSDK offboard demo for every vehicle. Ctrl-C shuts everything down.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import time

from sitl_bridge.autopilot import registry
from sitl_bridge.autopilot.fleet import AutopilotFault
from sitl_bridge.autopilot.px4 import Px4Error
from sitl_bridge.errors import ConfigError
from sitl_bridge.hil.errors import HilError
from sitl_bridge.hil.lockstep import parse_speed_factor
from sitl_bridge.session import SessionError, SimSession, default_world_path
from sitl_bridge.world.clock import nearest_whole_steps_s

RUNTIME_FAILURES: tuple[type[BaseException], ...] = (SessionError, HilError, Px4Error)
"""Failures reported as one message (exit 1) rather than a traceback."""

STATUS_PERIOD_S = 0.5
"""Wall seconds between status updates on a terminal (one line, rewritten in place)."""
LOG_STATUS_PERIOD_S = 10.0
"""Wall seconds between status lines when stdout is not a terminal (a log file)."""


def speed_factor_arg(text: str) -> float:
    """`--speed-factor`: a number >= 0, or `max` (= 0, as fast as possible)."""
    try:
        return parse_speed_factor(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number >= 0 or 'max', got {text!r}") from None


def _interrupt_on_sigterm() -> None:
    """SIGTERM (docker stop, a supervisor) shuts down as cleanly as Ctrl-C."""
    def handler(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    with contextlib.suppress(ValueError):  # not the main thread (tests calling main())
        signal.signal(signal.SIGTERM, handler)


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "run", help="run the simulator with autopilots and serve the MAVLink API",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("world", nargs="?", default=None,
                        help="world file (default: worlds/empty.yaml of the installation)")
    kinds = registry.names(session=True)
    parser.add_argument("--autopilot", choices=kinds, default="stub",
                        help="; ".join(f"{k}: {registry.get(k).help}" for k in kinds) + " (default stub)")
    parser.add_argument("--stub-process", action="store_true",
                        help="short for --autopilot stub-process")
    parser.add_argument("--px4-bin", default=os.environ.get("PX4_BIN"),
                        help="PX4 SITL binary (bin/px4 of px4_sitl_default; default: $PX4_BIN)")
    parser.add_argument("--px4-rootfs", default=None, help="PX4 ROMFS/etc directory (default: from the build tree)")
    parser.add_argument("--run-dir", default=None,
                        help="keep PX4's working directories and console logs here (default: a "
                             "temporary directory removed on exit)")
    parser.add_argument("--speed-factor", type=speed_factor_arg, default=1.0,
                        help="simulated seconds per wall second; 0 or 'max' = as fast as possible (default 1)")
    parser.add_argument("--vehicles", type=int, default=None,
                        help="number of vehicles (default: as many as the world defines)")
    parser.add_argument("--duration", type=float, default=None,
                        help="simulated seconds to run (default: until Ctrl-C; with --demo: until "
                             "the demo is done, or this long if it is longer)")
    parser.add_argument("--instance-base", type=int, default=0,
                        help="first vehicle instance (ports 4560+i, 14580+i -> 14540+i)")
    parser.add_argument("--seed", type=int, default=0, help="random seed of physics and sensors")
    parser.add_argument("--gui", action="store_true", help="open the pybullet GUI")
    parser.add_argument("--demo", action="store_true",
                        help="fly the built-in MAVSDK offboard demo with every vehicle, then exit")
    parser.add_argument("--quiet", action="store_true", help="no live status line")
    parser.add_argument("--policy", default=None, metavar="RUN_DIR_OR_CHECKPOINT",
                        help="fly this trained policy greedily in the world's scenario, through "
                             "MAVSDK and the chosen autopilot (stub or px4), then exit")
    parser.add_argument("--episodes", type=int, default=1, help="episodes to fly with --policy (default 1)")
    parser.add_argument("--video", metavar="FILE.mp4", default=None,
                        help="with --policy: record what the policy did (the `video` extra)")
    parser.add_argument("--restart-autopilot", action="store_true",
                        help="restart a dead or frozen autopilot (stub process or PX4) and keep "
                             "simulating, instead of exiting with status 1")
    parser.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    if args.vehicles is not None and args.vehicles < 1:
        print("sitl-bridge run: --vehicles must be at least 1", file=sys.stderr)
        return 2
    if args.duration is not None and not args.duration > 0:
        print("sitl-bridge run: --duration must be positive", file=sys.stderr)
        return 2
    _interrupt_on_sigterm()
    if args.stub_process:
        args.autopilot = "stub-process"
    if args.policy:
        return _run_policy(args)
    try:
        owns_autopilots = registry.session_kind(args.autopilot).fleet_class().owns_autopilots
        session = SimSession(
            args.world or default_world_path(),
            autopilot=args.autopilot,
            speed_factor=args.speed_factor,
            instance_base=args.instance_base,
            seed=args.seed,
            px4_bin=args.px4_bin,
            px4_rootfs=args.px4_rootfs,
            gui=args.gui,
            num_vehicles=args.vehicles,
            run_dir=args.run_dir,
            # autopilots started by hand: wait like Gazebo, however long it takes
            connect_timeout_s=60.0 if owns_autopilots else None,
        )
    except ConfigError as exc:
        print(f"sitl-bridge run: {exc}", file=sys.stderr)
        return 2
    _print_banner(session)
    try:
        with session:
            if args.demo:
                return _run_demo(session, args)
            return _serve(session, args)
    except KeyboardInterrupt:
        print("\ninterrupted; shut down cleanly", file=sys.stderr)
        return 130
    except ConfigError as exc:
        print(f"sitl-bridge run: {exc}", file=sys.stderr)
        return 2
    except RUNTIME_FAILURES as exc:
        # A busy port, an autopilot that died or never answered: say what, no traceback.
        print(f"sitl-bridge run: {exc}", file=sys.stderr)
        return 1


def _print_banner(session: SimSession) -> None:
    speed = "max" if session.speed_factor == 0 else f"{session.speed_factor:g}x"
    print(f"world {session.world.name}: {session.num_vehicles} vehicle(s), autopilot "
          f"{session.autopilot}, speed {speed}", flush=True)
    for k, instance in enumerate(session.instances):
        print(f"  vehicle {instance}: {session.ports(k).describe(session.host)}", flush=True)
    note = session.autopilots.describe()
    if note:
        print(note, flush=True)


def _serve(session: SimSession, args: argparse.Namespace) -> int:
    """Run until `--duration` simulated seconds (free-running: until Ctrl-C), printing status.
    With `--restart-autopilot` a dead or frozen autopilot is restarted (cold boot) and the
    simulation goes on; the restarts are logged and counted."""
    tty = sys.stdout.isatty()
    end_s = None if args.duration is None else session.time_s + args.duration
    _advance(session, end_s)
    last_line = time.monotonic()
    restarts = 0
    while True:
        try:
            done = session.wait_held(STATUS_PERIOD_S) if end_s is not None else False
            if end_s is None:
                time.sleep(STATUS_PERIOD_S)  # pacing the status line, not the simulation
            session.check()  # raises if the runner or an autopilot died
        except AutopilotFault as fault:
            if not args.restart_autopilot:
                raise
            restarts += 1
            _restart(session, fault, restarts, tty)
            _advance(session, end_s)
            continue
        if done:
            break
        if args.quiet:
            continue
        if tty:
            print(f"\r{session.status_line()}\033[K", end="", flush=True)
        elif time.monotonic() - last_line >= LOG_STATUS_PERIOD_S:
            print(session.status_line(), flush=True)
            last_line = time.monotonic()
    if tty and not args.quiet:
        print()
    print(session.status_line(), flush=True)
    restarted = f", {restarts} autopilot restart(s)" if args.restart_autopilot else ""
    print(f"done: {session.time_s:.2f} s simulated, real-time factor "
          f"{session.overall_real_time_factor:.1f}x{restarted}", flush=True)
    return 0


def _advance(session: SimSession, end_s: float | None) -> None:
    """Let the simulation run on: to `end_s` simulated seconds, or free-running."""
    if end_s is None:
        session.resume()
    elif end_s > session.time_s:
        session.run_for(nearest_whole_steps_s(end_s - session.time_s, session.step_us), wait=False)


def _restart(session: SimSession, fault: AutopilotFault, count: int, tty: bool) -> None:
    """Log a fault (its first line: a console tail follows in PX4's) and restart the autopilots."""
    first_line = str(fault).splitlines()[0] if str(fault) else fault.reason
    print(f"{chr(10) if tty else ''}[{session.time_s:8.2f} s] autopilot of vehicle {fault.instance} "
          f"{fault.reason} ({first_line}); restarting it (restart {count})", file=sys.stderr, flush=True)
    started = time.monotonic()
    # holds first, dropping what the dead link raises meanwhile (a hold of its own could fail on it)
    session.restart_autopilots()
    print(f"[{session.time_s:8.2f} s] autopilot of vehicle {fault.instance} ready again after "
          f"{time.monotonic() - started:.1f} s wall", file=sys.stderr, flush=True)


def _run_demo(session: SimSession, args: argparse.Namespace) -> int:
    """Fly the demo with every vehicle. With `--duration` longer than the demo took, the
    simulation then runs on (autopilots holding or landed) until that simulated time."""
    # mavsdk is only imported for the demo (it is slow to import for every other command)
    from sitl_bridge.client import Fleet, OffboardClientError, SimTimeoutError
    from sitl_bridge.client.demo import run_demo

    started = time.monotonic()
    sim_start = session.time_s
    try:
        with Fleet.for_session(session) as fleet:
            results = run_demo(fleet, report=lambda text: print(f"[{session.time_s:7.2f} s] {text}", flush=True))
    except (OffboardClientError, SimTimeoutError) as exc:
        raise SessionError(f"demo failed: {exc}") from exc
    wall = time.monotonic() - started
    sim = session.time_s - sim_start
    worst = max((r.error_m for r in results), default=0.0)
    print(f"demo done: {sim:.1f} s simulated in {wall:.2f} s wall "
          f"(real-time factor {sim / wall:.1f}x), worst leg error {worst:.2f} m", flush=True)
    if args.duration is not None and session.time_s < args.duration:
        session.run_for(nearest_whole_steps_s(args.duration - session.time_s, session.step_us))
    return 0


def _run_policy(args: argparse.Namespace) -> int:
    """Fly a trained policy greedily in the scenario's env, whose `stub`/`px4` backend sends
    every action as a MAVSDK offboard velocity setpoint: the same path a real vehicle takes."""
    if args.autopilot not in registry.names(session=True, env=True):
        print(f"sitl-bridge run: --policy needs --autopilot "
              f"{' or '.join(registry.names(session=True, env=True))}", file=sys.stderr)
        return 2
    # torch and mavsdk are only imported for this mode
    from sitl_bridge.rl.common.drones_env import DronesEnv, scenario_env_factory
    from sitl_bridge.rl.evaluation.evaluate import summarize
    from sitl_bridge.rl.evaluation.rollout import eval_seeds, rollout
    from sitl_bridge.rl.evaluation.video import VideoUnavailable
    from sitl_bridge.rl.learner.policy import policy_from_checkpoint
    from sitl_bridge.rl.training.run_dir import run_dir_of, run_scenario

    try:
        # The run's own scenario unless a world is named (a bare checkpoint file: the default world).
        world = str(args.world or (run_scenario(args.policy) if run_dir_of(args.policy) else default_world_path()))
        policy = policy_from_checkpoint(args.policy)
        print(f"flying {args.policy} greedily in {world} through MAVSDK and the {args.autopilot} autopilot: "
              f"{args.episodes} episode(s); starting the simulator...", flush=True)
        videos = None
        if args.video:
            from sitl_bridge.envs.scenario import load_scenario
            from sitl_bridge.rl.evaluation.video import EpisodeVideos

            videos = EpisodeVideos.into_file(args.video, load_scenario(world).task.render.fps)
        factory = scenario_env_factory(world, args.autopilot, speed_factor=args.speed_factor,
                                       instance_base=args.instance_base, px4_bin=args.px4_bin, gui=args.gui,
                                       render_mode="rgb_array_list" if videos is not None else None)
        env = DronesEnv(factory(args.seed))
        try:
            traces = rollout(env, policy, eval_seeds(args.seed, args.episodes), on_episode=_print_episode,
                             videos=videos)
        finally:
            env.close()
        if videos is not None:
            videos.close()
            print(f"video: {args.video}", flush=True)
    except KeyboardInterrupt:
        print("\ninterrupted; shut down cleanly", file=sys.stderr)
        return 130
    except (ConfigError, ValueError, FileNotFoundError, VideoUnavailable) as exc:  # wrong pairing, no extra
        print(f"sitl-bridge run: {exc}", file=sys.stderr)
        return 2
    except RUNTIME_FAILURES as exc:
        print(f"sitl-bridge run: {exc}", file=sys.stderr)
        return 1
    print(summarize(world, args.episodes, traces).summary(), flush=True)
    return 0


def _print_episode(traces: list) -> None:
    """One line per drone as soon as its episode ends (`run --policy` progress)."""
    for trace in traces:
        print(f"episode {trace.episode} drone {trace.drone}: {trace.outcome} after {trace.steps} steps, "
              f"reward {trace.reward:.0f}, {_actions_text(trace.actions)}", flush=True)


def _actions_text(actions: list) -> str:
    """Discrete codes in full; continuous commands (vectors) as their mean norm, one line."""
    if actions and isinstance(actions[0], list):
        import numpy as np

        return f"continuous commands, mean norm {float(np.mean(np.linalg.norm(actions, axis=1))):.2f}"
    return "actions " + " ".join(map(str, actions))
