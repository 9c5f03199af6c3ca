"""`sitl-bridge bench --link`: real-time factor of the lockstep HIL link.

The autopilot is the trivial `ConstantAutopilot` (answers every HIL_SENSOR at once), so the
figures are the cost of physics + sensors + the simulator protocol + lockstep itself, i.e. the
ceiling any autopilot can reach. Cases, all at speed factor 0 (as fast as lockstep allows):

- peer in the lockstep thread (a pump: how the stub runs), 1 and 2 vehicles;
- peer in another process (how PX4 runs: every step is a TCP round trip between processes);
- link only: precomputed sensor frames, no physics (the protocol's own cost per step);
- with PX4_BIN set: a real PX4 SITL (boot-to-ready and restart-to-ready wall times, and the
  real-time factor of PX4 hovering at speed factor 0 and at a few paced factors).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from sitl_bridge.hil import HilError, HilLink, Lockstep
from sitl_bridge.hil.peer import ConstantAutopilot
from sitl_bridge.physics.simulation import MotorCommand, Simulation
from sitl_bridge.sensors.suite import SensorSuite
from sitl_bridge.world.loader import load_world

WORLDS = Path(__file__).resolve().parents[2] / "worlds"


def _free_links(count: int, start: int = 3000) -> list[HilLink]:
    """`count` links on consecutive free instances (ports 4560+start... upward)."""
    for first in range(start, start + 400, count):
        links: list[HilLink] = []
        try:
            for k in range(count):
                links.append(HilLink(first + k))
            return links
        except HilError:
            for link in links:
                link.close()
    raise HilError("no free HIL ports for the benchmark")


class _ReplaySim:
    """Stands in for physics in the link-only case: time advances, nothing is computed."""

    def __init__(self, states: list[Any], step_us: int) -> None:
        self.states = states
        self.step_us = step_us
        self.time_us = 0

    def state(self, vehicle: int) -> Any:
        return self.states[vehicle]

    def step(self, commands: list[MotorCommand]) -> None:
        self.time_us += self.step_us


class _ReplaySensors:
    """Replays one second of real sensor frames (rates, GPS, mag, baro as in a real run)."""

    def __init__(self, frames: list[Any]) -> None:
        self.frames = frames
        self.index = 0

    def sample(self, state: Any, time_us: int) -> Any:
        frame = self.frames[self.index % len(self.frames)]
        self.index += 1
        frame.time_us = time_us
        return frame


def _case(name: str, vehicles: int, seconds: float, *, mode: str) -> dict[str, float]:
    world = load_world(WORLDS / ("empty.yaml" if vehicles == 1 else "two_drones_empty.yaml"))
    sim = Simulation(world)
    step_us = sim.step_us
    sensors: list[Any] = [SensorSuite(world.home, seed=i, step_us=step_us) for i in range(vehicles)]
    if mode == "link-only":
        frames = [[s.sample(sim.state(i), k * step_us) for k in range(250)] for i, s in enumerate(sensors)]
        states = [sim.state(i) for i in range(vehicles)]
        sim.close()
        sim = _ReplaySim(states, step_us)
        sensors = [_ReplaySensors(f) for f in frames]
    links = _free_links(vehicles)
    peers: list[ConstantAutopilot] = []
    processes: list[subprocess.Popen[bytes]] = []
    try:
        if mode == "process":
            for link in links:
                processes.append(subprocess.Popen(
                    [sys.executable, "-m", "sitl_bridge.hil.peer", "-i", str(link.instance),
                     "--base-port", str(link.port - link.instance)],
                    stdin=subprocess.DEVNULL,
                ))
        else:
            for link in links:
                peer = ConstantAutopilot(link.instance, base_port=link.port - link.instance)
                peer.connect()
                peers.append(peer)
        lockstep = Lockstep(sim, sensors, links, speed_factor=0, pumps=[p.pump for p in peers])
        if not lockstep.accept_all(30.0):
            raise HilError("benchmark peer did not connect")
        lockstep.run_for(0.2)  # actuators flowing, caches warm
        start, cpu_start = time.perf_counter(), time.thread_time()
        lockstep.run_for(seconds)
        wall, cpu = time.perf_counter() - start, time.thread_time() - cpu_start
        result = {
            "rtf": seconds / wall,
            "rtf_cpu": seconds / max(cpu, 1e-9),
            "us_per_step": wall / lockstep.steps_for(seconds) * 1e6,
            "timeouts": lockstep.stats.timeouts,
        }
        # rtf_cpu: simulated seconds per CPU second of the lockstep thread, i.e. what one
        # dedicated core gives (the fair figure on a shared machine; excludes a peer process)
        print(f"  {name:<44} {vehicles} veh  {result['rtf']:6.1f}x real time  "
              f"{result['rtf_cpu']:6.1f}x per CPU s  {result['us_per_step']:6.0f} us/step  "
              f"timeouts {result['timeouts']}")
        return result
    finally:
        for peer in peers:
            peer.close()
        for link in links:
            link.close()
        for process in processes:
            process.terminate()
            process.wait(5)
        if hasattr(sim, "close"):
            sim.close()


def _fly_then_reset_in_place(fleet: Any, lockstep: Lockstep) -> float:
    """Arm, take off, hover 10 s (printing the real-time factor of PX4 flying on its own
    controllers), then `reset_in_place`; returns its wall seconds."""
    from sitl_bridge.mavlink import dialect

    autopilot = fleet.autopilots[0]
    autopilot.command(dialect.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    lockstep.run_until(lambda: autopilot.poll().armed, max_seconds=5)
    nan = float("nan")
    autopilot.command(dialect.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, nan, nan, nan, nan)
    start, cpu_start = time.perf_counter(), time.thread_time()
    lockstep.run_for(10.0)
    wall, cpu = time.perf_counter() - start, time.thread_time() - cpu_start
    height_m = float(lockstep.sim.state(0).position_enu_m[2])
    print(f"  PX4 take-off and hover (at {height_m:.2f} m), speed factor max: {10.0 / wall:6.1f}x real time "
          f"(simulator thread {10.0 / max(cpu, 1e-9):.0f}x per CPU s), timeouts {lockstep.stats.timeouts}")
    return fleet.reset_in_place(lockstep)


def _px4_case(seconds: float) -> None:
    """Real PX4: ready times and real-time factors (needs PX4_BIN)."""
    from sitl_bridge.autopilot.px4 import Px4Config, Px4Fleet

    world = load_world(WORLDS / "empty.yaml")
    sim = Simulation(world)
    links = _free_links(1, start=1)
    instance = links[0].instance
    if instance > 9:  # PX4 maps API ports of instances >= 10 onto one port
        links[0].close()
        sim.close()
        print("  PX4: no free instance below 10, skipped")
        return
    lockstep = Lockstep(sim, [SensorSuite(world.home, seed=0)], links, speed_factor=0, actuator_timeout_s=5.0)
    with tempfile.TemporaryDirectory(prefix="sitl-bridge-bench-") as run_dir:
        config = Px4Config.create(None, run_dir, speed_factor=0, home=world.home)
        fleet = Px4Fleet(config, [instance])
        try:
            start = time.perf_counter()
            fleet.start()
            fleet.connect(links, 60)
            fleet.wait_ready(lockstep)
            boot_s = time.perf_counter() - start
            restart_s = fleet.restart(lockstep)
            print(f"  PX4 start-to-ready {boot_s:.2f} s wall, restart-to-ready {restart_s:.2f} s wall "
                  f"(sim reset + PX4 restart + estimator ready)")
            in_place_s = _fly_then_reset_in_place(fleet, lockstep)
            print(f"  PX4 in-place reset after a 2.5 m hover: {in_place_s:.2f} s wall until the estimate "
                  f"is back within 0.3 m (vs restart {restart_s:.2f} s)")
            fleet.restart(lockstep)
            for factor in (0.0, 1.0, 5.0, 10.0):
                lockstep.speed_factor = factor
                span = seconds if factor == 0 else min(seconds, 2.0 * factor)
                span = lockstep.steps_for_rounded(span) * sim.step_us / 1e6
                begin = time.perf_counter()
                lockstep.run_for(span)
                rtf = span / (time.perf_counter() - begin)
                label = "max" if factor == 0 else f"{factor:g}"
                print(f"  PX4 on the ground, speed factor {label:>4}: {rtf:6.1f}x real time, "
                      f"timeouts {lockstep.stats.timeouts}")
        finally:
            fleet.stop()
            links[0].close()
            sim.close()


def run(args: argparse.Namespace) -> int:
    """Run every case for `args.seconds` of simulated time and print the figures."""
    seconds = float(getattr(args, "seconds", 20.0))
    print(f"bench link: lockstep HIL link, trivial autopilot, speed factor 0, {seconds:g} s simulated per case")
    _case("physics + sensors + link, peer in-thread", 1, seconds, mode="pump")
    _case("physics + sensors + link, peer in-thread", 2, seconds, mode="pump")
    _case("physics + sensors + link, peer in a process", 1, seconds, mode="process")
    _case("physics + sensors + link, peer in a process", 2, seconds, mode="process")
    _case("link only (replayed frames), peer in-thread", 1, seconds, mode="link-only")
    if os.environ.get("PX4_BIN"):
        _px4_case(seconds)
    else:
        print("  PX4: set PX4_BIN to a px4_sitl_default bin/px4 to include a real PX4")
    return 0
