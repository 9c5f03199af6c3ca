"""`sitl-bridge bench --stub`: real-time factor of the full protocol path with the stub.

Simulator -> HIL link (TCP) -> in-process stub autopilot -> MAVLink API (UDP) -> MAVSDK, at
speed factor 0 (as fast as lockstep allows), for 1 and 2 vehicles. Two phases per case:
`ground` (disarmed, streams and MAVSDK connected) and `flying` (armed, hovering in OFFBOARD
with MAVSDK streaming velocity setpoints), each `--seconds` of simulated time in one run_for.
"""

from __future__ import annotations

import argparse
import time

from sitl_bridge.autopilot.allocation import claim_free_instances
from sitl_bridge.client.fleet import Fleet
from sitl_bridge.session import SimSession, default_world_path

BENCH_INSTANCE_BASE = 200
"""Benchmarks claim vehicle instances from here up: off the low ones users run."""


def measure(vehicles: int, seconds: float) -> dict[str, tuple[float, float, float]]:
    """{'ground': (rtf, rtf_sim_cpu, rtf_process_cpu), 'flying': ...} for `vehicles` stubs.

    `rtf`: simulated / wall seconds through the session's runner thread (what users get).
    `rtf_sim_cpu`: simulated seconds per CPU second of the thread running the lockstep (the
    same loop, run on the calling thread for the measurement): what one dedicated core gives,
    the fair figure on a loaded machine. `rtf_process_cpu`: per CPU second of the whole
    process, MAVSDK's threads included."""
    result: dict[str, tuple[float, float, float]] = {}
    with claim_free_instances(vehicles, BENCH_INSTANCE_BASE) as claim, \
            SimSession(default_world_path(), autopilot="stub", speed_factor=0, instance_base=claim,
                       num_vehicles=vehicles) as session, \
            Fleet.for_session(session) as fleet:
        fleet.wait_healthy()
        result["ground"] = _timed_run(session, seconds)
        fleet.arm()
        fleet.takeoff(2.5)
        fleet.start_offboard()
        result["flying"] = _timed_run(session, seconds)
        fleet.land()
    return result


def _timed_run(session: SimSession, seconds: float) -> tuple[float, float, float]:
    seconds = round(seconds / session.step_s) * session.step_s
    wall0 = time.perf_counter()
    session.run_for(seconds)
    wall = time.perf_counter() - wall0
    with session.exclusive():  # same lockstep loop, on this thread, to read its CPU time
        lockstep = session.lockstep
        assert lockstep is not None
        thread0, process0 = time.thread_time(), time.process_time()
        lockstep.run_for(seconds)
        thread_cpu, process_cpu = time.thread_time() - thread0, time.process_time() - process0
    return seconds / wall, seconds / max(thread_cpu, 1e-9), seconds / max(process_cpu, 1e-9)


def run(args: argparse.Namespace) -> int:
    seconds = float(getattr(args, "seconds", 20.0))
    print(f"bench stub: full protocol path (HIL TCP + stub + MAVLink UDP + MAVSDK), speed factor 0, "
          f"{seconds:g} s simulated per phase")
    for vehicles in (1, 2):
        rtf = measure(vehicles, seconds)
        for phase, (wall_rtf, thread_rtf, process_rtf) in rtf.items():
            print(f"  {vehicles} vehicle(s) {phase:<7} {wall_rtf:6.1f}x real time; per CPU second: "
                  f"{thread_rtf:6.1f}x (simulation thread = one core), {process_rtf:6.1f}x (whole process)",
                  flush=True)
    return 0
