"""Lidar on real pybullet: known distances, max range on no hit, own body ignored, flags, filter."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from sitl_bridge.physics import MotorCommand, Simulation
from sitl_bridge.sensors.lidar import Lidar, LidarConfig, ray_directions_flu, ray_labels
from sitl_bridge.sensors.ray_reach import REACH_MARGIN_M, rays_that_may_hit
from sitl_bridge.world import load_world

WORLDS = Path(__file__).resolve().parents[1] / "worlds"


@pytest.fixture
def obstacle_sim():
    with Simulation(load_world(WORLDS / "obstacle.yaml")) as sim:
        yield sim


def test_default_layout_is_the_thesis_lidar():
    config = LidarConfig()
    h, u, d = ray_directions_flu(config)
    assert (len(h), len(u), len(d), config.range_m) == (35, 6, 6, 5.0)
    assert np.allclose(h[17], (1, 0, 0))            # middle ray looks forward
    assert np.allclose(np.linalg.norm(np.vstack((h, u, d)), axis=1), 1.0)
    assert np.all(u[:, 2] > 0.7) and np.all(d[:, 2] < -0.7)


def test_reads_a_box_at_a_known_distance(obstacle_sim):
    block = obstacle_sim.world.obstacles[0]
    face_y = block.position_m[1] - block.shape.size_m[1] / 2   # south face of the block
    obstacle_sim.place_vehicle(0, (0.0, face_y - 2.0, 1.5), yaw_enu_rad=math.pi / 2)  # facing north
    scan = Lidar(obstacle_sim).scan()[0]
    assert scan.horizontal_m[17] == pytest.approx(2.0, abs=0.01)
    assert scan.down_m.min() == pytest.approx(1.5 / math.cos(math.radians(7.5)), abs=0.01)
    assert scan.min_m == pytest.approx(2.0, abs=0.01) and not scan.near
    # turn to face east: the block is now on the left (ray at +90 deg, counter-clockwise)
    obstacle_sim.place_vehicle(0, (0.0, face_y - 2.0, 1.5), yaw_enu_rad=0.0)
    h = Lidar(obstacle_sim).scan()[0].horizontal_m
    angles = np.degrees(np.arctan2(*ray_directions_flu(LidarConfig())[0][:, 1::-1].T))
    left = int(np.argmin(np.abs(angles - 90.0)))
    assert h[left] == pytest.approx(2.0 / math.cos(math.radians(angles[left] - 90.0)), abs=0.01)


def test_no_hit_is_max_range_never_inf_or_nan():
    with Simulation(load_world(WORLDS / "empty.yaml")) as sim:
        sim.place_vehicle(0, (0, 0, 3.0))
        scan = Lidar(sim).scan()[0]
        # the rays start inside the vehicle's own box and must not see it
        assert np.all(scan.horizontal_m == 5.0) and np.all(scan.up_m == 5.0)
        assert np.all(np.isfinite(scan.down_m)) and np.all(scan.down_m > 2.9)
        sim.place_vehicle(0, (0, 0, 30.0))
        far = Lidar(sim).scan()[0]
        assert np.all(far.down_m == 5.0) and far.min_m == 5.0 and not far.near and not far.crash


def test_near_and_crash_flags(obstacle_sim):
    block = obstacle_sim.world.obstacles[0]
    face_y = block.position_m[1] - block.shape.size_m[1] / 2
    lidar = Lidar(obstacle_sim, LidarConfig(near_m=1.0, crash_m=0.4))
    for distance, near, crash in ((1.5, False, False), (0.8, True, False), (0.3, True, True)):
        obstacle_sim.place_vehicle(0, (0.0, face_y - distance, 1.5), yaw_enu_rad=math.pi / 2)
        scan = lidar.scan()[0]
        assert (scan.near, scan.crash) == (near, crash), distance
    # the down rays do not raise flags by default (resting on the ground is no crash)
    obstacle_sim.place_vehicle(0, (0, -2, 0.06))
    assert not lidar.scan()[0].near


def test_configurable_counts_and_fields_of_view(obstacle_sim):
    config = LidarConfig(horizontal_rays=8, horizontal_fov_deg=90, up_rays=0, down_rays=3, down_fov_deg=0,
                         range_m=10.0, flag_groups=("horizontal", "down"))
    obstacle_sim.place_vehicle(0, (0, 0, 2.0), yaw_enu_rad=math.pi / 2)
    scan = Lidar(obstacle_sim, config).scan()[0]
    assert (len(scan.horizontal_m), len(scan.up_m), len(scan.down_m)) == (8, 0, 3)
    assert np.allclose(scan.down_m, 2.0, atol=0.01) and scan.min_m == pytest.approx(2.0, abs=0.01)
    assert np.all(scan.horizontal_m[3:5] < 10.0)  # the block ahead is within 10 m
    assert np.all(scan.horizontal_m <= 10.0)


def test_moving_average_filter(obstacle_sim):
    block = obstacle_sim.world.obstacles[0]
    face_y = block.position_m[1] - block.shape.size_m[1] / 2
    lidar = Lidar(obstacle_sim, LidarConfig(filter_window=2))
    obstacle_sim.place_vehicle(0, (0.0, face_y - 2.0, 1.5), yaw_enu_rad=math.pi / 2)
    assert lidar.scan()[0].horizontal_m[17] == pytest.approx(2.0, abs=0.01)
    obstacle_sim.place_vehicle(0, (0.0, face_y - 1.0, 1.5), yaw_enu_rad=math.pi / 2)
    assert lidar.scan()[0].horizontal_m[17] == pytest.approx(1.5, abs=0.01)  # mean of 2.0 and 1.0
    lidar.reset()
    assert lidar.scan()[0].horizontal_m[17] == pytest.approx(1.0, abs=0.01)


def test_two_vehicles_in_one_batch_see_each_other():
    with Simulation(load_world(WORLDS / "two_drones_empty.yaml")) as sim:
        sim.place_vehicle(0, (0, 0, 3.0), yaw_enu_rad=math.pi / 2)    # facing north
        sim.place_vehicle(1, (0, 3.0, 3.0), yaw_enu_rad=-math.pi / 2)  # facing south, 3 m away
        scans = Lidar(sim).scan()
        half_width = 0.47 / 2
        for scan in scans:
            assert scan.horizontal_m[17] == pytest.approx(3.0 - half_width, abs=0.01)
        sim.step([MotorCommand.disarmed()] * 2)
        assert len(Lidar(sim).scan()) == 2


def test_wrong_number_of_configs_is_an_error(obstacle_sim):
    with pytest.raises(ValueError, match="expected 1 lidar configs"):
        Lidar(obstacle_sim, [LidarConfig(), LidarConfig()])


def test_mesh_obstacle_is_loaded_and_seen(tmp_path):
    # a 2 m cube as a Wavefront OBJ next to the world file
    corners = [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
    faces = [(1, 3, 4, 2), (5, 6, 8, 7), (1, 2, 6, 5), (3, 7, 8, 4), (1, 5, 7, 3), (2, 4, 8, 6)]
    obj = "".join(f"v {x} {y} {z}\n" for x, y, z in corners)
    obj += "".join(f"f {a} {b} {c}\nf {a} {c} {d}\n" for a, b, c, d in faces)
    (tmp_path / "cube.obj").write_text(obj)
    (tmp_path / "mesh.yaml").write_text(
        "world:\n  name: mesh\n  workspace: {min: [-10, -10, 0], max: [10, 10, 5]}\n"
        "  vehicles: [{name: d, spawn: {position: [0, 0, 1.0], yaw: 90}}]\n"
        "  obstacles: [{name: cube, shape: mesh, file: cube.obj, size: [2, 2, 2], position: [0, 4, 1]}]\n")
    world = load_world(tmp_path / "mesh.yaml")
    assert world.obstacles[0].shape.mesh_file == str(tmp_path / "cube.obj")
    with Simulation(world) as sim:
        assert Lidar(sim).scan()[0].horizontal_m[17] == pytest.approx(3.0, abs=0.01)


def test_per_vehicle_configs_in_one_batch():
    with Simulation(load_world(WORLDS / "two_drones_empty.yaml")) as sim:
        sim.place_vehicle(0, (0, 0, 3.0), yaw_enu_rad=math.pi / 2)
        sim.place_vehicle(1, (0, 3.0, 3.0), yaw_enu_rad=-math.pi / 2)
        small = LidarConfig(horizontal_rays=5, horizontal_fov_deg=40, up_rays=0, down_rays=1, down_fov_deg=0)
        scans = Lidar(sim, [LidarConfig(), small]).scan()
        assert [len(s.horizontal_m) for s in scans] == [35, 5]
        assert scans[1].horizontal_m[2] == pytest.approx(3.0 - 0.47 / 2, abs=0.01)
        assert scans[1].down_m.tolist() == pytest.approx([3.0], abs=0.01)


def test_ray_labels_name_each_direction_as_it_points() -> None:
    config = LidarConfig()
    labels = ray_labels(config)
    horizontal, up, down = ray_directions_flu(config)
    assert [len(labels[g]) for g in ("horizontal", "up", "down")] == [len(horizontal), len(up), len(down)]
    assert labels["horizontal"][17] == "ahead" and labels["horizontal"][0] == "behind"
    for label, (_, y, _) in zip(labels["horizontal"], horizontal, strict=True):
        if label.endswith("left"):
            assert y > 0.0   # FLU: +y is the body's left
        elif label.endswith("right"):
            assert y < 0.0
    for group, rays, where in (("up", up, "above"), ("down", down, "below")):
        for label, (x, _, _) in zip(labels[group], rays, strict=True):
            assert label.startswith(where) and (label.endswith("ahead") == (x > 0.1))


def _random_quaternion(rng: np.random.Generator, max_tilt_rad: float) -> tuple[float, ...]:
    """A random heading with a random tilt up to `max_tilt_rad` (w, x, y, z; ENU/FLU)."""
    yaw, tilt, axis = rng.uniform(-math.pi, math.pi), rng.uniform(0.0, max_tilt_rad), rng.uniform(-math.pi, math.pi)
    qz = (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))
    qt = (math.cos(tilt / 2), math.cos(axis) * math.sin(tilt / 2), math.sin(axis) * math.sin(tilt / 2), 0.0)
    w1, x1, y1, z1 = qz
    w2, x2, y2, z2 = qt
    return (w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2)


@pytest.mark.parametrize("world", ["obstacle.yaml", "window.yaml", "street.yaml", "two_drones_window.yaml"])
def test_the_pruned_scan_is_the_full_cast_bit_for_bit(world: str) -> None:
    """Casting only the rays whose segment meets a bounding box or the ground gives the same
    scans as casting every ray: ranges, flags and who caused a crash, anywhere in the workspace
    (near the ground, inside the clutter, tilted), with movers and other vehicles about."""
    rng = np.random.default_rng(4)
    with Simulation(load_world(WORLDS / world), seed=2) as sim:
        pruned, full = Lidar(sim), Lidar(sim)
        full.prune = False
        low, high = np.array(sim.world.workspace.min_m), np.array(sim.world.workspace.max_m)
        skipped = 0
        for k in range(150):
            for i in range(sim.num_vehicles):
                position = rng.uniform(low, high)
                position[2] = rng.uniform(0.05, min(high[2], 6.0))
                if i and k % 3 == 0:  # now and then right beside the first vehicle
                    position = np.array(sim.state(0).position_enu_m) + rng.uniform(-0.6, 0.6, 3)
                sim.place_vehicle(i, position, quaternion_enu_flu=_random_quaternion(rng, 0.6))
            if k % 10 == 0:  # movers move on
                sim.step([MotorCommand.disarmed()] * sim.num_vehicles)
            for a, b in zip(pruned.scan(), full.scan(), strict=True):
                for group in ("horizontal_m", "up_m", "down_m"):
                    np.testing.assert_array_equal(getattr(a, group), getattr(b, group))
                assert (a.near, a.crash, a.min_m, a.crash_by_vehicles) == (b.near, b.crash, b.min_m,
                                                                           b.crash_by_vehicles)
            boxes, owners = sim.body_boxes()
            skipped += int(np.sum(~rays_that_may_hit(pruned._starts, pruned._ends, pruned._owners, boxes, owners,
                                                     sim.has_ground, REACH_MARGIN_M)))
        assert skipped > 0  # the prune does skip rays (else this test compares a cast with itself)


def test_a_ray_is_cast_only_when_it_may_reach_something():
    boxes = np.array([[1.0, -1.0, 0.0, 2.0, 1.0, 2.0], [-0.2, -0.2, 0.8, 0.2, 0.2, 1.2]])
    owners = np.array([-1, 0])  # the second box is vehicle 0's own body
    starts = np.zeros((5, 3)) + (0.0, 0.0, 1.0)
    ends = starts + np.array([[5.0, 0, 0], [-5.0, 0, 0], [0, 0, 5.0], [0, 0, -0.95], [0, 0, -1.5]])
    ray_owner = np.zeros(5, dtype=np.int64)
    may = rays_that_may_hit(starts, ends, ray_owner, boxes, owners, True, REACH_MARGIN_M)
    # east: the box; west, up: nothing (the own body does not count); down 0.95 m: within the
    # margin of the ground; down 1.5 m: through it
    assert may.tolist() == [True, False, False, True, True]
    assert rays_that_may_hit(starts, ends, ray_owner + 1, boxes, owners, False, 0.0).tolist() == [True] * 5
    ends[1, 0] = math.nan
    assert rays_that_may_hit(starts, ends, ray_owner, boxes, owners, False, 0.0)[1]
