"""Dynamic obstacles: patrol and random legs follow their paths, face their motion, never fall."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pybullet as p
import pytest

from sitl_bridge.physics import MotorCommand, Simulation
from sitl_bridge.physics.movers import Patrol, RandomLegs
from sitl_bridge.world import PatrolMover, RandomLegsMover, load_world

WORLDS = Path(__file__).resolve().parents[1] / "worlds"


def test_patrol_goes_back_and_forth_at_its_speed():
    mover = Patrol(PatrolMover(((0, 0, 1), (10, 0, 1)), speed_m_s=2.0))
    mover.reset(np.random.default_rng(0))
    xs = []
    for _ in range(1000):  # 10 s at 10 ms: out (5 s) and back (5 s)
        pose = mover.pose()
        xs.append(pose.position_m[0])
        assert pose.position_m[1:] == (0.0, 1.0)
        assert math.hypot(*pose.velocity_m_s) == pytest.approx(2.0)
        mover.advance(0.01)
    assert max(xs) == pytest.approx(10.0, abs=0.03) and xs[0] == 0.0
    assert xs[250] == pytest.approx(5.0) and xs[750] == pytest.approx(5.0)
    # facing: east on the way out, west on the way back
    mover.reset(np.random.default_rng(0))
    mover.advance(1.0)
    assert mover.pose().yaw_rad == pytest.approx(0.0)
    mover.advance(5.0)
    assert abs(mover.pose().yaw_rad) == pytest.approx(math.pi)
    assert mover.pose().position_m[0] == pytest.approx(8.0)


def _start(spec: PatrolMover, seed: int) -> tuple[tuple[float, float, float], float]:
    mover = Patrol(spec)
    mover.reset(np.random.default_rng(seed))
    pose = mover.pose()
    return pose.position_m, pose.yaw_rad


def test_patrol_random_start_is_seeded_and_off_by_default():
    points = ((0.0, 0.0, 1.0), (10.0, 0.0, 1.0))
    # default: the first point whatever the seed, and the shared mover stream is not drawn from
    fixed = PatrolMover(points, speed_m_s=2.0)
    assert {_start(fixed, seed)[0] for seed in range(5)} == {(0.0, 0.0, 1.0)}
    rng = np.random.default_rng(3)
    Patrol(fixed).reset(rng)
    assert rng.uniform() == np.random.default_rng(3).uniform()
    # random_start: same seed, same start; different seeds, different starts; on the route
    spec = PatrolMover(points, speed_m_s=2.0, random_start=True)
    assert _start(spec, 7) == _start(spec, 7)
    starts = [_start(spec, seed) for seed in range(20)]
    assert len({position for position, _ in starts}) == 20
    assert all(0.0 <= position[0] <= 10.0 and position[1:] == (0.0, 1.0) for position, _ in starts)
    # the route is out and back: some draws start walking east, some west
    assert {round(abs(yaw)) for _, yaw in starts} == {0, 3}
    # then it walks on at its speed from there
    mover = Patrol(spec)
    mover.reset(np.random.default_rng(7))
    before = mover.pose()
    mover.advance(0.1)
    assert math.dist(before.position_m, mover.pose().position_m) == pytest.approx(0.2)


def test_patrol_random_start_from_the_world_file(tmp_path: Path):
    text = (WORLDS / "street.yaml").read_text()
    world = load_world(WORLDS / "street.yaml")
    walkers = [o for o in world.obstacles if isinstance(o.mover, PatrolMover)]
    assert walkers and all(o.mover.random_start for o in walkers)  # street: no memorisable timing

    def starts(seed: int) -> list[tuple[float, ...]]:
        with Simulation(world, seed=seed) as sim:
            bodies = sim.obstacle_bodies
            return [p.getBasePositionAndOrientation(bodies[o.name], physicsClientId=sim.client_id)[0]
                    for o in walkers]

    assert starts(4) == starts(4) != starts(5)
    # the key is optional and off by default
    plain = tmp_path / "plain.yaml"
    plain.write_text(text.replace("random_start: true", "random_start: false"))
    assert not any(o.mover.random_start for o in load_world(plain).obstacles if isinstance(o.mover, PatrolMover))


def test_random_legs_stay_in_their_cuboid_at_their_speed():
    spec = RandomLegsMover((-2, -3, 5), (2, 3, 8), speed_m_s=5.0)
    mover = RandomLegs(spec, start_m=(0, 0, 6))
    mover.reset(np.random.default_rng(1))
    previous = mover.pose().position_m
    targets = set()
    for _ in range(2000):
        mover.advance(0.004)
        pose = mover.pose()
        assert all(lo - 1e-9 <= x <= hi + 1e-9 for x, lo, hi in zip(pose.position_m, spec.min_m, spec.max_m, strict=True))
        assert math.dist(previous, pose.position_m) <= 5.0 * 0.004 + 1e-9
        targets.add(tuple(round(v, 6) for v in pose.velocity_m_s))
        previous = pose.position_m
    assert len(targets) > 3  # several legs flown
    # seeded: same seed, same flight
    a, b = RandomLegs(spec, (0, 0, 6)), RandomLegs(spec, (0, 0, 6))
    a.reset(np.random.default_rng(9))
    b.reset(np.random.default_rng(9))
    for _ in range(500):
        a.advance(0.004)
        b.advance(0.004)
    assert a.pose().position_m == b.pose().position_m


def test_street_movers_in_pybullet_face_motion_and_do_not_fall():
    world = load_world(WORLDS / "street.yaml")
    with Simulation(world, seed=2) as sim:
        bodies = sim.obstacle_bodies
        cid = sim.client_id
        movers = {o.name: o for o in world.obstacles if o.mover}
        last = {n: p.getBasePositionAndOrientation(bodies[n], physicsClientId=cid)[0] for n in movers}
        walked = dict.fromkeys(movers, 0.0)
        for k in range(3 * 250):
            sim.step([MotorCommand.disarmed()])
            if k % 25 == 24:  # path length, not net displacement: a bird may turn back
                for n in movers:
                    now = p.getBasePositionAndOrientation(bodies[n], physicsClientId=cid)[0]
                    walked[n] += math.dist(now, last[n])
                    last[n] = now
        for name, spec in movers.items():
            pos, orn = p.getBasePositionAndOrientation(bodies[name], physicsClientId=cid)
            vel, _ = p.getBaseVelocity(bodies[name], physicsClientId=cid)
            assert walked[name] > 0.8 * 3 * spec.mover.speed_m_s, name  # it moved at its speed
            forward = p.getMatrixFromQuaternion(orn)[0::3]  # body x axis in world
            speed = math.hypot(*vel)
            assert speed == pytest.approx(spec.mover.speed_m_s, rel=0.05), name
            assert np.dot(forward, vel) / speed == pytest.approx(1.0, abs=1e-2), name  # faces its motion
            if isinstance(spec.mover, PatrolMover):
                assert pos[2] == pytest.approx(spec.position_m[2], abs=1e-3), name  # gravity off
                xs = [pt[0] for pt in spec.mover.points_m]
                ys = [pt[1] for pt in spec.mover.points_m]
                assert min(xs) - 1e-6 <= pos[0] <= max(xs) + 1e-6 and min(ys) - 1e-6 <= pos[1] <= max(ys) + 1e-6
            else:
                lo, hi = spec.mover.min_m, spec.mover.max_m
                assert all(a - 0.05 <= x <= b + 0.05 for x, a, b in zip(pos, lo, hi, strict=True)), name
            assert p.getDynamicsInfo(bodies[name], -1, physicsClientId=cid)[0] > 0  # not static


def test_vehicle_hit_by_a_pedestrian_is_a_collision():
    world = load_world(WORLDS / "street.yaml")
    walker = next(o for o in world.obstacles if o.name == "pedestrian_1")
    (ax, ay, _), (bx, by, _) = walker.mover.points_m[0], walker.mover.points_m[-1]
    with Simulation(world, seed=0) as sim:
        # stand on the middle of pedestrian_1's walk: it passes there within half a round trip,
        # wherever this episode started it
        sim.place_vehicle(0, ((ax + bx) / 2.0, (ay + by) / 2.0, 0.06))
        names = set()
        half_trip_s = math.hypot(bx - ax, by - ay) / walker.mover.speed_m_s
        for _ in range(int((half_trip_s + 1.0) * 250)):
            sim.step([MotorCommand.disarmed()])
            names |= {c.other for c in sim.collisions() if c.kind == "obstacle"}
        assert "pedestrian_1" in names
