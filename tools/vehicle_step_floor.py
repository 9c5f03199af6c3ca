#!/usr/bin/env python3
"""Where a `direct` / `batched` vehicle-step goes, and the floor that pybullet's API sets.

Measured in one process, in CPU time (this process's own work, so a shared machine's load
changes the figures less than wall time), on the bench's scenario (worlds/obstacle.yaml):

* bare: one `stepSimulation` of the bench's reference world (plane + one body; `bench`'s `physics`);
* the pybullet calls every vehicle makes every physics step: `stepSimulation` of its own client,
  the state read (`getBasePositionAndOrientation` + `getBaseVelocity`, each a full actual-state
  request) and the wrench (`applyExternalForce` + `applyExternalTorque`); and `stepSimulation` per
  copy when COPIES copies share one client 1 km apart (the "one world" design);
* the fused `direct` loop (`DirectBackend.run_steps`) per physics step in steady flight, and per
  flown physics step with episode starts counted as the bench counts them (an in-place reset flies
  ~1200 physics steps of take-off that are no flown time);
* the bound that the pybullet calls alone put on `batched` (aggregate, one core) as a fraction of
  bare: every other part of a vehicle-step (sensors, estimator, commander, controllers, mixer,
  rotors, collision tests and the Python between them) must fit in what is left.

    python tools/vehicle_step_floor.py [--seconds 10] [--episodes-s 120]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from sitl_bridge.bench.physics import STEP_US, bare_pybullet_rtf  # noqa: E402
from sitl_bridge.data_paths import worlds_dir  # noqa: E402
from sitl_bridge.envs import make_env  # noqa: E402
from sitl_bridge.physics import IrisParams, Simulation  # noqa: E402
from sitl_bridge.physics.bodies import create_ground, create_obstacle, create_vehicle  # noqa: E402
from sitl_bridge.physics.bullet import p  # noqa: E402
from sitl_bridge.world import load_world  # noqa: E402

SCENARIO = worlds_dir() / "obstacle.yaml"
COPIES = 16


def cpu_us(run, calls: int) -> float:
    """CPU microseconds per call of `run(calls)`, best of three (load only ever adds)."""
    best = float("inf")
    for _ in range(3):
        start = time.process_time()
        run(calls)
        best = min(best, time.process_time() - start)
    return best / calls * 1e6


def pybullet_calls(calls: int) -> dict[str, float]:
    """CPU us of each pybullet call a vehicle-step makes, on the scenario's own world."""
    world = load_world(SCENARIO)
    with Simulation(world, seed=0) as sim:
        sim.place_vehicle(0, (0.0, 0.0, 1e5))  # falls freely for the whole measurement: no contacts
        cid, body = sim.client_id, sim.vehicle_bodies[0]

        def step(n: int) -> None:
            for _ in range(n):
                p.stepSimulation(physicsClientId=cid)

        def read(n: int) -> None:
            for _ in range(n):
                p.getBasePositionAndOrientation(body, physicsClientId=cid)
                p.getBaseVelocity(body, physicsClientId=cid)

        def wrench(n: int) -> None:
            for _ in range(n):
                p.applyExternalForce(body, -1, (0.0, 0.0, 15.0), (0.0, 0.0, 1e5), p.WORLD_FRAME, physicsClientId=cid)
                p.applyExternalTorque(body, -1, (0.0, 0.0, 0.0), p.WORLD_FRAME, physicsClientId=cid)

        figures = {"step (own client)": cpu_us(step, calls), "read pose + velocity": cpu_us(read, calls),
                   "apply force + torque": cpu_us(wrench, calls)}
    figures["step, per copy, one shared client"] = shared_world_step_us(world, calls)
    return figures


def shared_world_step_us(world, calls: int) -> float:  # noqa: ANN001
    """`stepSimulation` per copy with COPIES copies of the world's bodies 1 km apart in one client."""
    cid = p.connect(p.DIRECT)
    try:
        p.setGravity(0.0, 0.0, -world.physics.gravity_m_s2, physicsClientId=cid)
        p.setPhysicsEngineParameter(fixedTimeStep=STEP_US * 1e-6, numSubSteps=0,
                                    numSolverIterations=world.physics.solver_iterations,
                                    deterministicOverlappingPairs=0, physicsClientId=cid)
        create_ground(cid)
        for k in range(COPIES):
            for spec in world.obstacles:
                x, y, z = spec.position_m
                create_obstacle(cid, spec.shape, (x + 1000.0 * k, y, z), 0.0, spec.color_rgba)
            create_vehicle(cid, IrisParams(), (1000.0 * k, 0.0, 1e5), 0.0)

        def step(n: int) -> None:
            for _ in range(n // COPIES):
                p.stepSimulation(physicsClientId=cid)

        return cpu_us(step, calls)
    finally:
        p.disconnect(physicsClientId=cid)


def fused_loop(steps: int, episodes_s: float) -> tuple[float, float, float]:
    """(CPU us per physics step in steady flight, CPU us per flown physics step with resets
    counted, physics steps per flown step) of one `direct` env with random actions."""
    env = make_env(SCENARIO, autopilot="direct", seed=0)
    try:
        env.reset(seed=0)
        backend = env.unwrapped.backend
        backend.set_velocities([(0.3, 0.2, 0.0)])
        steady = cpu_us(backend.run_steps, steps)
        env.reset(seed=0)
        rng = np.random.default_rng(0)
        step_s = env.unwrapped.scenario.task.action.step_s
        flown_s, physics0, start = 0.0, backend.steps, time.process_time()
        while flown_s < episodes_s:
            _, _, terminated, truncated, _ = env.step(int(rng.integers(8)))
            flown_s += step_s
            if terminated or truncated:
                env.reset()
        flown = flown_s * 1e6 / backend.sim.step_us
        per_flown = (time.process_time() - start) / flown * 1e6
        return steady, per_flown, (backend.steps - physics0) / flown
    finally:
        env.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0, help="simulated seconds per pybullet figure")
    parser.add_argument("--episodes-s", type=float, default=120.0, help="flown seconds of random episodes")
    args = parser.parse_args()
    calls = int(args.seconds * 1e6 / STEP_US)
    bare = 1e6 / (max(bare_pybullet_rtf(args.seconds)[1] for _ in range(3)) * 1e6 / STEP_US)
    api = pybullet_calls(calls)
    steady, per_flown, factor = fused_loop(calls, args.episodes_s)
    own = api["step (own client)"] + api["read pose + velocity"] + api["apply force + torque"]
    shared = own - api["step (own client)"] + api["step, per copy, one shared client"]
    print(f"CPU us per vehicle physics step (x bare = multiples of one bare step, {bare:.2f} us)")
    for name, us in [("bare stepSimulation", bare), *api.items(), ("pybullet calls, own client", own),
                     ("pybullet calls, shared client", shared), ("fused direct loop, steady flight", steady),
                     (f"fused direct loop per flown step (x{factor:.2f} steps: resets)", per_flown)]:
        print(f"  {name:<58} {us:7.2f} us  {us / bare:6.2f} x bare")
    print(f"batched fraction of bare if only the pybullet calls cost anything: own clients "
          f"{bare / (own * factor):.2f}, shared client {bare / (shared * factor):.2f}; "
          f"today's loop: {bare / per_flown:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
