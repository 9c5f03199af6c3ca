"""World files: all shipped worlds load, bad files give one clear line, layouts randomise."""

from __future__ import annotations

import argparse
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sitl_bridge.commands import worlds as worlds_command
from sitl_bridge.errors import ConfigError, Node
from sitl_bridge.world import load_world, realize
from sitl_bridge.world.layout import horizontal_radius_m

WORLDS = Path(__file__).resolve().parents[1] / "worlds"
SHIPPED = ("empty", "random_goal", "obstacle", "random_obstacle", "two_drones_empty", "window",
           "two_drones_window", "street")


def run_check(*files: str) -> int:
    parser = argparse.ArgumentParser()
    worlds_command.register(parser.add_subparsers())
    args = parser.parse_args(["worlds", "check", *files])
    return args.func(args)


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_world_loads(name):
    world = load_world(WORLDS / f"{name}.yaml")
    assert world.name == name
    assert world.vehicles and all(v.model == "iris" for v in world.vehicles)
    assert all(v.goal is not None for v in world.vehicles)
    for v in world.vehicles:
        assert world.workspace.contains(v.spawn.position_m)


def test_thesis_geometry_facts():
    two = load_world(WORLDS / "two_drones_empty.yaml")
    # head-on: each goal is the other's start (horizontally)
    g0, g1 = two.goals[two.vehicles[0].goal], two.goals[two.vehicles[1].goal]
    assert g0.center_m[:2] == two.vehicles[1].spawn.position_m[:2]
    assert g1.center_m[:2] == two.vehicles[0].spawn.position_m[:2]
    window = load_world(WORLDS / "window.yaml")
    wall = next(o for o in window.obstacles if o.shape.opening is not None)
    # flying over is impossible: the workspace ends at the wall top
    assert window.workspace.max_m[2] <= wall.position_m[2] + wall.shape.size_m[2] / 2
    street = load_world(WORLDS / "street.yaml")
    kinds = {type(o.mover).__name__ for o in street.obstacles if o.mover}
    assert kinds == {"PatrolMover", "RandomLegsMover"}


def test_street_van_always_blocks_the_line_and_no_mover_passes_through_it():
    street = load_world(WORLDS / "street.yaml")
    ceiling = street.workspace.max_m[2]
    birds = [o for o in street.obstacles if o.mover is not None and o.shape.kind == "sphere"]
    walkers = [o for o in street.obstacles if o.mover is not None and o.shape.kind == "cylinder"]
    rng = np.random.default_rng(0)
    for _ in range(300):
        layout = realize(street, rng)
        van = next(o for o in layout.obstacles if o.name == "van")
        (x, y, _), (sx, sy, sz) = van.position_m, van.shape.size_m
        assert sz >= ceiling - 0.1  # no flight level over it
        # the straight start-goal line runs through it (lidar crash distance 0.4 m): no constant action passes
        (x0, y0, _), (x1, y1, _) = layout.spawn_positions_m[0], layout.goals[0].center_m
        line_x = x0 + (x1 - x0) * (y - y0) / (y1 - y0)
        assert x - sx / 2 - 0.4 < line_x < x + sx / 2 + 0.4
        for bird in birds:  # pigeons fly beside it, never through it
            lo, hi = bird.mover.min_m, bird.mover.max_m
            r = bird.shape.radius_m
            assert lo[0] - r > x + sx / 2 or hi[0] + r < x - sx / 2 or lo[2] - r > sz
        for walker in walkers:  # the crossings are clear of it
            crossing = {p[1] for p in walker.mover.points_m[1:3]}
            assert all(abs(cy - y) > sy / 2 + walker.shape.radius_m for cy in crossing)


def test_worlds_check_passes_for_all_shipped(capsys):
    files = [str(WORLDS / f"{n}.yaml") for n in SHIPPED]
    assert run_check(*files) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == len(SHIPPED)
    assert all(": ok: " in line for line in lines)


def broken_copy(tmp_path: Path, edit, name: str = "window.yaml") -> Path:
    """A copy of a shipped world with `edit(data)` applied to its parsed YAML."""
    data = yaml.safe_load((WORLDS / name).read_text())
    edit(data)
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def test_broken_copy_gives_one_line_and_exit_1(tmp_path, capsys):
    def edit(data):
        data["world"]["obstacles"][1]["size"] = [1, 2]

    path = broken_copy(tmp_path, edit)
    assert run_check(str(path), str(WORLDS / "empty.yaml")) == 1
    captured = capsys.readouterr()
    assert captured.err == f"{path}: world.obstacles[1].size: expected 3 positive numbers, got [1, 2]\n"
    assert captured.out.count("\n") == 1 and "empty" in captured.out


def test_real_cli_check(tmp_path):
    path = broken_copy(tmp_path, lambda data: data["world"]["obstacles"][0].update(sise=3))
    result = subprocess.run([sys.executable, "-m", "sitl_bridge", "worlds", "check", str(path)],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 1
    assert result.stderr.strip().splitlines() == [f"{path}: world.obstacles[0].sise: unknown key "
                                                  f"(expected one of {', '.join(sorted(_obstacle_keys()))})"]
    ok = subprocess.run([sys.executable, "-m", "sitl_bridge", "worlds", "check", *map(str, WORLDS.glob("*.yaml"))],
                        capture_output=True, text=True, timeout=60)
    assert ok.returncode == 0, ok.stderr


def _obstacle_keys() -> set[str]:
    from sitl_bridge.world.loader import SHAPE_KEYS
    return SHAPE_KEYS | {"name", "position", "yaw", "color", "mover", "mass", "randomize"}


def _set(*keys_and_value):
    *keys, last, value = keys_and_value

    def edit(data):
        node = data
        for k in keys:
            node = node[k]
        node[last] = value
    return edit


@pytest.mark.parametrize(("edit", "message"), [
    (_set("world", "vehicles", 0, "goal", "inside"),
     "world.vehicles[0].goal: expected the name of a goal in world.goals (outside), got 'inside'"),
    (_set("world", "vehicles", 0, "model", "x500"), "world.vehicles[0].model: expected one of iris, got 'x500'"),
    (_set("world", "workspace", "max", [4, 8, -1]),
     "world.workspace.max: expected 3 numbers each greater than workspace.min [-4.0, -4.0, 0.0], got [4, 8, -1]"),
    (_set("world", "obstacles", 0, "opening", "bottom", 5.5),
     "world.obstacles[0].opening: expected an opening inside the wall"),
    (_set("world", "obstacles", 0, "shape", "pyramid"),
     "world.obstacles[0].shape: expected one of box, cylinder, sphere, wall, mesh, got 'pyramid'"),
    (_set("extra", 1), "extra: unknown key (expected one of task, train, world)"),
    (_set("world", "vehicles", 0, "spawn", "position", [0, 0, -3]),
     "world.vehicles[0].spawn.position: expected a position inside the workspace"),
    (_set("world", "vehicles", 0, "lidar", {"near": 0.5, "crash": 0.8}),
     "world.vehicles[0].lidar.crash: expected a distance not above near (0.5), got 0.8"),
])
def test_bad_files_fail_with_one_clear_line(tmp_path, edit, message):
    path = broken_copy(tmp_path, edit)
    with pytest.raises(ConfigError) as info:
        load_world(path)
    text = str(info.value)
    assert "\n" not in text
    assert text.startswith(f"{path}: {message}")


def test_malformed_yaml_and_missing_world(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("world: [unclosed\n")
    with pytest.raises(ConfigError, match="invalid YAML"):
        load_world(bad)
    bad.write_text("task: {}\n")
    with pytest.raises(ConfigError, match="world: required key is missing"):
        load_world(bad)


def test_task_and_train_sections_are_kept_raw(tmp_path):
    path = tmp_path / "scenario.yaml"
    path.write_text((WORLDS / "empty.yaml").read_text() + "task:\n  steps: 20\ntrain:\n  gamma: 0.8\n")
    world = load_world(path)
    assert isinstance(world.task, Node) and world.task.get("steps").integer() == 20
    assert world.task.path == "task"
    assert world.train.get("gamma").number() == 0.8


def test_random_goal_is_redrawn_inside_its_box():
    world = load_world(WORLDS / "random_goal.yaml")
    rng = np.random.default_rng(3)
    g = world.goals[0]
    centers = {realize(world, rng).goals[0].center_m for _ in range(20)}
    assert len(centers) == 20
    for c in centers:
        assert all(lo <= x <= hi for x, lo, hi in zip(c, g.randomize_min_m, g.randomize_max_m, strict=True))
    # fixed goal stays fixed
    empty = load_world(WORLDS / "empty.yaml")
    assert realize(empty, rng).goals[0].center_m == empty.goals[0].center_m


def test_random_obstacle_lies_on_the_path_and_changes_shape():
    world = load_world(WORLDS / "random_obstacle.yaml")
    rng = np.random.default_rng(5)
    kinds = set()
    for _ in range(100):
        layout = realize(world, rng)
        start = np.array(layout.spawn_positions_m[0][:2])
        goal = np.array(layout.goal_of(0).center_m[:2])
        placed = layout.obstacles[0]
        kinds.add(placed.shape.kind)
        xy = np.array(placed.position_m[:2])
        direction = (goal - start) / np.linalg.norm(goal - start)
        along = float(np.dot(xy - start, direction)) / np.linalg.norm(goal - start)
        offset = xy - start
        lateral = abs(float(direction[0] * offset[1] - direction[1] * offset[0]))
        assert 0.35 - 1e-9 <= along <= 0.65 + 1e-9
        assert lateral <= 0.5 + 1e-9
        assert math.isclose(placed.position_m[2], placed.shape.half_height_m)  # rests on the ground
        clearance = horizontal_radius_m(placed.shape) + 0.5  # never on the spawn or in the goal
        assert np.linalg.norm(xy - start) > clearance and np.linalg.norm(xy - goal) > clearance
    assert kinds == {"box", "cylinder", "sphere"}


def test_same_seed_same_layout():
    world = load_world(WORLDS / "random_obstacle.yaml")
    a = realize(world, np.random.default_rng(11))
    b = realize(world, np.random.default_rng(11))
    assert a == b


def test_spawn_randomisation_stays_in_its_ranges(tmp_path):
    def edit(data):
        data["world"]["vehicles"][0]["spawn"]["randomize"] = {"position": [1.0, 0.5, 0.0], "yaw": 20}

    world = load_world(broken_copy(tmp_path, edit, name="empty.yaml"))
    spawn = world.vehicles[0].spawn
    rng = np.random.default_rng(0)
    layouts = [realize(world, rng) for _ in range(50)]
    positions = np.array([lay.spawn_positions_m[0] for lay in layouts])
    yaws = np.array([lay.spawn_yaws_rad[0] for lay in layouts])
    assert np.all(np.abs(positions - spawn.position_m) <= (1.0, 0.5, 0.0))
    assert positions[:, 0].std() > 0.2 and np.all(positions[:, 2] == spawn.position_m[2])
    assert np.all(np.abs(yaws - spawn.yaw_rad) <= math.radians(20)) and yaws.std() > 0.05
    assert "randomised: spawn" in world.summary()


def test_worlds_check_build_builds_every_world_in_pybullet(capsys):
    parser = argparse.ArgumentParser()
    worlds_command.register(parser.add_subparsers())
    args = parser.parse_args(["worlds", "check", "--build", *(str(WORLDS / f"{n}.yaml") for n in SHIPPED)])
    assert args.func(args) == 0
    assert capsys.readouterr().out.count(": ok: ") == len(SHIPPED)


def _paths(node, prefix=()):
    """Every key path inside a parsed YAML document."""
    yield prefix
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from _paths(v, (*prefix, i))


JUNK = st.one_of(st.none(), st.booleans(), st.integers(-5, 5), st.floats(allow_nan=True), st.text(max_size=5),
                 st.lists(st.integers(-3, 3), max_size=4), st.dictionaries(st.text(max_size=3), st.integers(), max_size=2))


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_any_corruption_is_a_one_line_config_error_never_a_crash(tmp_path, data):
    name = data.draw(st.sampled_from(SHIPPED))
    doc = yaml.safe_load((WORLDS / f"{name}.yaml").read_text())
    doc.pop("task", None)
    doc.pop("train", None)
    paths = [p for p in _paths(doc["world"], ("world",)) if len(p) > 1]
    path = data.draw(st.sampled_from(paths))
    junk = data.draw(JUNK)
    node = doc
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = junk
    file = tmp_path / "fuzz.yaml"
    file.write_text(yaml.safe_dump(doc))
    try:
        load_world(file)
    except ConfigError as exc:
        assert "\n" not in str(exc) and str(exc).startswith(f"{file}: ")
