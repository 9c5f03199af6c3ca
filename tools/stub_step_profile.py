"""Where one physics step's CPU goes on the stub protocol path (one vehicle flying).

Sets up what `sitl-bridge bench --stub` flies (SimSession with the in-process stub, MAVSDK
connected, armed, hovering in OFFBOARD with setpoints streaming), then, with the session's runner
thread off the lockstep, runs the lockstep on this thread and reports:

* `thread_cpu_us`: this thread's CPU time per physics step (`time.thread_time`, the figure a
  loaded machine does not distort), median of `--reps` runs of `--seconds` simulated seconds;
* a breakdown per component: the same runs with a timer around each component's method,
  in thread CPU (`time.thread_time_ns`, a syscall: each timed call adds ~0.5 us of its own,
  so the total exceeds `thread_cpu_us`) and in wall time (`perf_counter_ns`: includes the
  time other threads, e.g. MAVSDK's woken by a datagram, take this core), children subtracted
  from their parents so that the lines add up to the step;
* with `--cprofile N`: the N functions with the most own time, under cProfile.

Usage: PYTHONPATH=. python tools/stub_step_profile.py [--seconds 10] [--reps 5] [--json F]
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import statistics
import time
from collections.abc import Callable
from typing import Any

from method_timers import timed_methods  # tools/ is on sys.path when run as a script

from sitl_bridge.autopilot.allocation import claim_free_instances
from sitl_bridge.bench.stub import BENCH_INSTANCE_BASE
from sitl_bridge.client.fleet import Fleet
from sitl_bridge.session import SimSession, default_world_path

# (component, parent or "", path of the object from the namespace below, method name)
TIMED = (
    ("step", "", "lockstep", "step"),
    ("sim: physics", "step", "sim", "step"),
    ("sim: sensors", "step", "suite", "sample_values"),
    ("sim: ground truth", "step", "suite", "ground_truth"),
    ("sim: HIL encode + send", "step", "link", "send_sensor_values"),
    ("sim: HIL send (syscall)", "sim: HIL encode + send", "link", "_send"),
    ("sim: HIL receive + decode", "step", "link", "poll"),
    ("sim: HIL decode", "sim: HIL receive + decode", "link", "_handle_bytes"),
    ("stub: pump", "step", "hil", "pump"),
    ("stub: handle bytes", "stub: pump", "hil", "_handle_bytes"),
    ("stub: parse", "stub: handle bytes", "parser", "feed"),
    ("stub: decode sensor", "stub: handle bytes", "hil", "_decode_sensor"),
    ("stub: decode gps", "stub: handle bytes", "hil", "_decode_gps"),
    ("stub: step", "stub: handle bytes", "hil", "_step"),
    ("stub: autopilot.update", "stub: step", "autopilot", "update"),
    ("stub: estimator", "stub: autopilot.update", "estimator", "update"),
    ("stub: prepare", "stub: autopilot.update", "autopilot", "prepare"),
    ("stub: commander", "stub: prepare", "commander", "step"),
    ("stub: outer loop", "stub: prepare", "autopilot", "_outer_loop"),
    ("stub: send (syscall)", "stub: step", "hil", "_send"),
    ("stub: API pump", "stub: pump", "api", "pump"),
    ("stub: API receive", "stub: API pump", "api", "_receive"),
    ("stub: API streams", "stub: API pump", "api", "_send_streams"),
    ("stub: API flush", "stub: API pump", "api", "_flush"),
)
# the stub's fused step (`hil_fused.FusedSensorStep.handle`, when the stub has one) calls
# `prepare` and `_send` itself, without `_step` and `update` around them
_FUSED_PARENTS = {"stub: prepare": "stub: fused step", "stub: send (syscall)": "stub: fused step"}
FUSED_TIMED = tuple((name, _FUSED_PARENTS.get(name, parent), path, method) for name, parent, path, method in TIMED) \
    + (("stub: fused step", "stub: handle bytes", "fused", "handle"),)


def _objects(session: SimSession) -> dict[str, Any]:
    lockstep = session.lockstep
    assert lockstep is not None
    vehicle = session.autopilots.vehicles[0]  # type: ignore[attr-defined]
    hil = vehicle.hil
    return {"lockstep": lockstep, "sim": lockstep.sim, "suite": lockstep.sensors[0], "link": lockstep.links[0],
            "hil": hil, "parser": hil._parser, "autopilot": vehicle.autopilot,
            "estimator": vehicle.autopilot.estimator, "commander": vehicle.autopilot.commander, "api": vehicle.api,
            "fused": getattr(hil, "_fused", None)}


def _timer_cost_ns(clock: Callable[[], int], n: int = 20000) -> tuple[float, float]:
    """(ns a timer adds inside its own interval, ns it adds to its caller's) per timed call,
    from timing an empty method the way `_timers` does."""
    def empty() -> None:
        pass

    inside = 0
    t0 = clock()
    for _ in range(n):
        empty()
    bare = clock() - t0
    t0 = clock()
    for _ in range(n):
        t = clock()
        try:
            empty()
        finally:
            inside += clock() - t
    total = clock() - t0
    return (inside - bare) / n, (total - inside) / n


def _exclusive_ns(totals: dict[str, int], calls: dict[str, int], cost: tuple[float, float],
                  timed: tuple[tuple[str, str, str, str], ...] = TIMED) -> dict[str, float]:
    """Own time per component: children subtracted, the timers' own cost taken out."""
    c_in, c_out = cost
    own: dict[str, float] = {name: totals[name] - calls[name] * c_in for name in totals}
    for name, parent, *_ in timed:
        if parent:
            own[parent] -= totals[name] + calls[name] * c_out
    return own


def _thread_cpu_us(session: SimSession, seconds: float) -> float:
    lockstep = session.lockstep
    assert lockstep is not None
    steps = lockstep.steps_for(seconds)
    t0 = time.thread_time()
    lockstep.run_for(seconds)
    return (time.thread_time() - t0) / steps * 1e6


def profile(seconds: float, reps: int, cprofile_top: int) -> dict[str, Any]:
    """The figures described in the module docstring."""
    out: dict[str, Any] = {}
    with claim_free_instances(1, BENCH_INSTANCE_BASE) as claim, \
            SimSession(default_world_path(), autopilot="stub", speed_factor=0, instance_base=claim,
                       num_vehicles=1) as session, Fleet.for_session(session) as fleet:
        fleet.wait_healthy()
        fleet.arm()
        fleet.takeoff(2.5)
        fleet.start_offboard()
        session.run_for(2.0)  # settle into the hover
        step_s = session.step_s
        seconds = round(seconds / step_s) * step_s
        with session.exclusive():
            cpu = [_thread_cpu_us(session, seconds) for _ in range(reps)]
            out["thread_cpu_us"] = {"median": statistics.median(cpu), "min": min(cpu), "max": max(cpu)}
            objects = _objects(session)
            timed = TIMED if objects["fused"] is None else FUSED_TIMED
            steps = session.lockstep.steps_for(seconds)  # type: ignore[union-attr]
            for kind, clock in (("cpu", time.thread_time_ns), ("wall", time.perf_counter_ns)):
                runs = []
                cost = _timer_cost_ns(clock)
                out[f"{kind}_timer_cost_ns"] = cost
                for _ in range(reps):
                    with timed_methods(objects, timed, clock) as (totals, calls):
                        session.lockstep.run_for(seconds)  # type: ignore[union-attr]
                    runs.append(_exclusive_ns(totals, calls, cost, timed))
                # per component, the median over the runs
                out[f"{kind}_us_per_step"] = {name: statistics.median(run[name] for run in runs) / steps / 1e3
                                              for name in runs[0]}
            if cprofile_top:
                prof = cProfile.Profile(time.thread_time)  # CPU, not the core others take
                prof.runcall(session.lockstep.run_for, seconds)  # type: ignore[union-attr]
                stats = pstats.Stats(prof)
                stats.sort_stats("tottime")
                rows = []
                for func, (_cc, ncalls, tottime, cumtime, _callers) in stats.stats.items():  # type: ignore[attr-defined]
                    rows.append((tottime, cumtime, ncalls, f"{func[0].split('sitl_bridge/')[-1]}:{func[1]}({func[2]})"))
                rows.sort(reverse=True)
                out["cprofile_us_per_step"] = [
                    {"own": t / steps * 1e6, "cum": c / steps * 1e6, "calls_per_step": n / steps, "where": w}
                    for t, c, n, w in rows[:cprofile_top]]
        fleet.land()
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0, help="simulated seconds per run")
    parser.add_argument("--reps", type=int, default=5, help="thread-CPU runs (median)")
    parser.add_argument("--cprofile", type=int, default=0, metavar="N", help="also list the top N functions")
    parser.add_argument("--json", help="write the figures to this file")
    args = parser.parse_args()
    result = profile(args.seconds, args.reps, args.cprofile)
    cpu = result["thread_cpu_us"]
    print(f"thread CPU per physics step: {cpu['median']:.1f} us (min {cpu['min']:.1f}, max {cpu['max']:.1f})")
    print("us per physics step, own time (children subtracted), median of the runs:")
    print(f"  {'component':<28} {'thread CPU':>10} {'wall':>8}")
    cpu_us, wall_us = result["cpu_us_per_step"], result["wall_us_per_step"]
    for name in cpu_us:
        print(f"  {name:<28} {cpu_us[name]:10.2f} {wall_us[name]:8.2f}")
    print(f"  {'total':<28} {sum(cpu_us.values()):10.2f} {sum(wall_us.values()):8.2f}")
    print(f"  (timer cost per call, ns inside/outside: cpu {result['cpu_timer_cost_ns']}, "
          f"wall {result['wall_timer_cost_ns']})")
    for row in result.get("cprofile_us_per_step", []):
        print(f"  {row['own']:7.2f} own {row['cum']:7.2f} cum {row['calls_per_step']:5.2f}/step  {row['where']}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
