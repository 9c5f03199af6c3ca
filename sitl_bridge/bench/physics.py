"""`sitl-bridge bench --physics`: real-time factor of physics + sensors (+ lidar), 1 and 2 vehicles.

Vehicles hover in the air at the hover input (so contacts do not dominate); every step runs
`Simulation.step` and `SensorSuite.sample` per vehicle, and the lidar scans at the given rate.
A bare pybullet loop (ground plane + one body, no Python work) is the reference for the ratios.
"""

from __future__ import annotations

import argparse
import contextlib
import time
from collections.abc import Iterator
from pathlib import Path

from sitl_bridge.physics import IrisParams, MotorCommand, Simulation
from sitl_bridge.physics.bullet import p
from sitl_bridge.sensors import SensorSuite
from sitl_bridge.sensors.lidar import Lidar
from sitl_bridge.world import World, load_world
from sitl_bridge.world.clock import DEFAULT_STEP_US

WORLDS_DIR = Path(__file__).resolve().parents[2] / "worlds"
STEP_US = DEFAULT_STEP_US
"""The benchmark's step: the default world's (250 Hz), whatever the world file says."""


@contextlib.contextmanager
def bare_world() -> Iterator[tuple[int, int]]:
    """A pybullet client with the bare reference world (ground plane + one body in the air,
    gravity on, 250 Hz); yields (client id, body id). The body falls at 15 m/s (pybullet's
    damping): it lands, and its steps cost three times as much, after about 6600 simulated s."""
    cid = p.connect(p.DIRECT)
    try:
        p.setGravity(0, 0, -9.8066, physicsClientId=cid)
        p.setTimeStep(STEP_US * 1e-6, physicsClientId=cid)
        p.createMultiBody(0, p.createCollisionShape(p.GEOM_PLANE, physicsClientId=cid), physicsClientId=cid)
        col = p.createCollisionShape(p.GEOM_BOX, halfExtents=[0.235, 0.235, 0.055], physicsClientId=cid)
        body = p.createMultiBody(1.55, col, basePosition=[0, 0, 1e5], physicsClientId=cid)  # never lands
        p.changeDynamics(body, -1, activationState=p.ACTIVATION_STATE_DISABLE_SLEEPING, physicsClientId=cid)
        yield cid, body
    finally:
        p.disconnect(physicsClientId=cid)


def bare_pybullet_rtf(seconds: float) -> tuple[float, float]:
    """(real-time factor, CPU real-time factor) of pybullet alone in `bare_world` for `seconds`
    simulated seconds."""
    with bare_world() as (cid, _):
        steps = int(seconds * 1e6 / STEP_US)
        start = time.perf_counter()
        cpu_start = time.process_time()
        for _ in range(steps):
            p.stepSimulation(physicsClientId=cid)
        return seconds / (time.perf_counter() - start), seconds / max(time.process_time() - cpu_start, 1e-9)


def sim_rtf(world: World, seconds: float, lidar_hz: float | None) -> tuple[float, float, float]:
    """(real-time factor, CPU real-time factor, wall microseconds per step) of step + sensors
    (+ lidar at lidar_hz). The CPU factor divides by this process's CPU time, so it stays
    meaningful on a machine shared with other busy processes."""
    with Simulation(world, seed=0, step_us=STEP_US) as sim:
        for i in range(sim.num_vehicles):
            position, _ = sim.pose(i)
            sim.place_vehicle(i, (position[0], position[1], 2.4), sim.layout.spawn_yaws_rad[i],
                              rotor_speeds_rad_s=sim.hover_rotor_speeds_rad_s())
        suites = [SensorSuite(world.home, seed=i, step_us=STEP_US) for i in range(sim.num_vehicles)]
        lidar = Lidar(sim) if lidar_hz else None
        lidar_every = max(1, round(1e6 / (lidar_hz * STEP_US))) if lidar_hz else 0
        u = IrisParams().hover_input(world.physics.gravity_m_s2)
        commands = [MotorCommand((u, u, u, u), True)] * sim.num_vehicles
        steps = int(seconds * 1e6 / STEP_US)
        start = time.perf_counter()
        cpu_start = time.process_time()
        for k in range(steps):
            sim.step(commands)
            t = sim.time_us
            for i, suite in enumerate(suites):
                suite.sample(sim.state(i), t)
            if lidar is not None and k % lidar_every == 0:
                lidar.scan()
        wall = time.perf_counter() - start
        cpu = max(time.process_time() - cpu_start, 1e-9)
    return seconds / wall, seconds / cpu, wall / steps * 1e6


def best_of(repeats: int, measure, *args):
    """The best of a few runs: other processes only ever make a run slower."""
    return max((measure(*args) for _ in range(repeats)), key=lambda r: r[0])


def run(args: argparse.Namespace) -> int:
    """Print the real-time factors (best of 3 runs each); return 0."""
    seconds = float(getattr(args, "seconds", 20.0))
    one = load_world(WORLDS_DIR / "obstacle.yaml")
    two = load_world(WORLDS_DIR / "two_drones_window.yaml")
    bare, bare_cpu = best_of(3, bare_pybullet_rtf, seconds)
    print(f"bench physics: {seconds:g} simulated s per case, step {STEP_US} us (250 Hz), best of 3;")
    print("  real-time factor = simulated s / wall s; per CPU s in brackets (robust to a busy machine)")
    print(f"  {'bare pybullet (plane + 1 body, no Python work)':<44} {bare:6.0f}x  [{bare_cpu:6.0f}x]")
    cases = [
        ("1 vehicle, sensors, no lidar", one, None),
        ("1 vehicle, sensors, lidar 10 Hz", one, 10.0),
        ("1 vehicle, sensors, lidar 50 Hz", one, 50.0),
        ("1 vehicle, sensors, lidar 250 Hz", one, 250.0),
        ("2 vehicles, sensors, lidar 10 Hz", two, 10.0),
        ("2 vehicles, sensors, lidar 250 Hz", two, 250.0),
    ]
    for label, world, lidar_hz in cases:
        rtf, rtf_cpu, us = best_of(3, sim_rtf, world, seconds, lidar_hz)
        print(f"  {label:<44} {rtf:6.0f}x  [{rtf_cpu:6.0f}x]  {us:6.1f} us/step  "
              f"({rtf_cpu / bare_cpu:.2f} of bare)")
    return 0
