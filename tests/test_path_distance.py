"""Path-distance shaping (`closer_to_goal: {along: path}`, envs/path_distance.py): the field on
layouts with a known answer, its continuity, the layout cache, the reward in the `direct`
backend on two_blocks, and one-line errors. Real pybullet, numba and stub autopilot."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from sitl_bridge.envs import make_env
from sitl_bridge.envs.path_distance import PathGrid, path_field
from sitl_bridge.envs.rewards import parse_rewards
from sitl_bridge.errors import ConfigError, Node
from sitl_bridge.world import GoalPlacement, Obstacle, ObstaclePlacement, Opening, Shape, Workspace

ROOT = Path(__file__).resolve().parents[1]
TWO_BLOCKS = ROOT / "experiments" / "generalization" / "two_blocks.yaml"
CELL = PathGrid().cell_m

WORKSPACE = Workspace((-5.0, -5.0, 0.0), (5.0, 5.0, 4.0))
GOAL = GoalPlacement("goal", (0.0, 3.0, 2.0), (1.0, 1.0, 1.0))
# A wall across the whole workspace (and above it) along y = 0, 0.3 m thick, with one slot from
# x = 2.05 to 3.65, full height: grown by the 0.4 m clearance it leaves x in [2.45, 3.25] free.
SLOT = Opening(offset_m=2.85, bottom_m=0.0, width_m=1.6, height_m=6.0)


def placed(name: str, shape: Shape, position: tuple[float, float, float], yaw: float = 0.0,
           **spec) -> ObstaclePlacement:
    return ObstaclePlacement(name, shape, position, yaw, Obstacle(name, shape, position, yaw, **spec))


def slotted_wall(x: float = 0.0) -> ObstaclePlacement:
    return placed("wall", Shape("wall", size_m=(12.0, 0.3, 6.0), opening=SLOT), (x, 0.0, 3.0))


def box_distance(point) -> float:
    gap = np.abs(np.asarray(point) - GOAL.center_m) - np.asarray(GOAL.size_m) / 2.0
    return float(np.linalg.norm(np.maximum(gap, 0.0)))


def test_free_space_gives_the_straight_distance() -> None:
    field = path_field(WORKSPACE, (), GOAL)
    rng = np.random.default_rng(0)
    for point in rng.uniform(WORKSPACE.min_m, WORKSPACE.max_m, size=(200, 3)):
        assert field.distance(point) == pytest.approx(box_distance(point), abs=0.1 * CELL), point
    assert field.distance(GOAL.center_m) == 0.0


def test_a_wall_with_one_gap_gives_the_detour_through_it() -> None:
    field = path_field(WORKSPACE, (slotted_wall(),), GOAL)
    start = np.array([0.0, -3.0, 2.0])
    # the detour around the grown slot's corners (2.45, -0.55) and (2.45, 0.55) to the goal box's
    # corner (0.5, 2.5): the true shortest path, round the grown corners, is a little shorter
    detour = (math.dist((0.0, -3.0), (2.45, -0.55)) + 1.1 + math.dist((2.45, 0.55), (0.5, 2.5)))
    assert field.distance(start) == pytest.approx(detour, abs=CELL)
    assert field.distance(start) > box_distance(start) + 1.5  # far longer than the straight line
    # a point in the slot: straight on to the goal
    assert field.distance((2.85, 0.0, 2.0)) == pytest.approx(math.dist((2.85, 0.0), (0.5, 2.5)), abs=CELL)
    # inside the grown wall (and in the wall itself): the nearest free node plus the way to it
    inside = field.distance((0.0, 0.0, 2.0))
    assert math.isfinite(inside) and inside > field.distance((0.0, 0.7, 2.0))
    # outside the workspace: finite, and farther than the nearest point inside
    assert field.distance((0.0, -7.0, 2.0)) > field.distance((0.0, -5.0, 2.0))


def test_the_distance_falls_continuously_along_the_path() -> None:
    field = path_field(WORKSPACE, (slotted_wall(),), GOAL)
    corners = [(0.0, -3.0, 2.0), (2.85, -1.0, 2.0), (2.85, 1.0, 2.0), (0.3, 2.7, 2.0)]
    legs = zip(corners[:-1], corners[1:], strict=True)
    points = np.concatenate([np.linspace(a, b, 60, endpoint=False) for a, b in legs]
                            + [np.array([corners[-1]])])
    values = np.array([field.distance(point) for point in points])
    steps = np.linalg.norm(np.diff(points, axis=0), axis=1)
    change = np.diff(values)
    # continuous: never more than the way flown, but for a few cm where the cell beside a grown
    # obstacle changes (a corner there is blocked, so the candidates of the query change)
    assert np.all(np.abs(change) <= steps + 0.1)
    assert np.mean(np.abs(change) <= steps + 1e-6) > 0.95
    assert np.all(change <= 0.01) and change.sum() < -6.0    # and falls all the way
    assert values[-1] < 0.2


def test_yawed_cylinder_sphere_and_box_block_their_space() -> None:
    obstacles = (placed("pillar", Shape("cylinder", radius_m=0.5, height_m=6.0), (-3.0, 0.0, 3.0)),
                 placed("ball", Shape("sphere", radius_m=0.8), (3.0, -2.0, 2.0)),
                 placed("slab", Shape("box", size_m=(3.0, 0.2, 6.0)), (0.0, -1.0, 3.0), yaw=math.radians(45)))
    field = path_field(WORKSPACE, obstacles, GOAL)
    free = field.occupancy.free

    def is_free(point) -> bool:
        index = np.round((np.asarray(point) - WORKSPACE.min_m) / CELL).astype(int)
        return bool(free[tuple(index)])

    assert not is_free((-3.0, 0.0, 2.0)) and not is_free((-3.5, 0.0, 1.0)) and is_free((-4.0, 0.0, 2.0))
    assert not is_free((3.0, -2.0, 3.0)) and is_free((3.0, -2.0, 3.5)) and is_free((4.5, -2.0, 2.0))
    assert not is_free((1.0, 0.0, 2.0)) and not is_free((-1.0, -2.0, 2.0)) and is_free((1.0, -2.0, 2.0))


def test_a_mesh_blocks_the_space_round_its_surface(tmp_path: Path) -> None:
    corners = [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
    faces = [(1, 2, 4, 3), (5, 7, 8, 6), (1, 5, 6, 2), (3, 4, 8, 7), (1, 3, 7, 5), (2, 6, 8, 4)]
    obj = tmp_path / "cube.obj"
    obj.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in corners)
                   + "".join(f"f {a} {b} {c}\nf {a} {c} {d}\n" for a, b, c, d in faces))
    mesh = Shape("mesh", size_m=(2.0, 2.0, 2.0), mesh_file=str(obj))
    free = path_field(WORKSPACE, (placed("house", mesh, (0.0, -3.0, 1.0)),), GOAL).occupancy.free

    def is_free(point) -> bool:
        return bool(free[tuple(np.round((np.asarray(point) - WORKSPACE.min_m) / CELL).astype(int))])

    assert not is_free((1.0, -3.0, 1.0)) and not is_free((0.0, -2.0, 2.0)) and not is_free((0.0, -4.0, 0.5))
    assert is_free((0.0, -1.5, 1.0)) and is_free((2.0, -3.0, 1.0)) and is_free((0.0, -3.0, 2.5))
    # a static mesh collides as a triangle surface (concave houses), so its inside is free, as
    # it is to a drone that got in through a door
    assert is_free((0.0, -3.0, 1.0))


def test_moving_obstacles_are_ignored() -> None:
    from sitl_bridge.world import PatrolMover

    walker = placed("walker", Shape("box", size_m=(2.0, 2.0, 4.0)), (0.0, 0.0, 2.0),
                    mover=PatrolMover(((0.0, 0.0, 2.0), (1.0, 0.0, 2.0)), 1.0))
    assert path_field(WORKSPACE, (walker,), GOAL).occupancy.free.all()


def test_fields_are_cached_by_layout() -> None:
    wall = slotted_wall()
    first = path_field(WORKSPACE, (wall,), GOAL)
    assert path_field(WORKSPACE, (slotted_wall(),), GOAL) is first   # same layout: no new work
    moved = path_field(WORKSPACE, (slotted_wall(x=-1.0),), GOAL)   # the slot moved 1 m west
    assert moved is not first and moved.occupancy is not first.occupancy
    start = (0.0, -3.0, 2.0)
    assert moved.distance(start) < first.distance(start) - 0.5
    other_goal = GoalPlacement("goal", (-2.0, 3.0, 2.0), (1.0, 1.0, 1.0))
    again = path_field(WORKSPACE, (wall,), other_goal)             # only the goal moved
    assert again is not first and again.occupancy is first.occupancy
    assert path_field(WORKSPACE, (wall,), GOAL, PathGrid(clearance_m=0.2)).occupancy is not first.occupancy


def _closer_terms(env, actions: list[int], seed: int) -> list[float]:
    env.reset(seed=seed)
    terms = []
    for action in actions:
        _, _, terminated, truncated, info = env.step(action)
        assert info["outcome"] is None, info
        terms.append(info["reward_terms"]["closer_to_goal"])
    return terms


def test_two_blocks_pays_for_flying_round_the_first_block() -> None:
    env = make_env(TWO_BLOCKS)
    try:
        (term,) = [t for t in env.scenario.task.rewards if t.name == "closer_to_goal"]
        assert term.path == PathGrid()
        # east, along the first block (its straight-line distance grows), then north into its gap
        east_then_north = _closer_terms(env, [0, 0, 3, 3, 3], seed=0)
        assert all(value > 0.0 for value in east_then_north), east_then_north
        # south, away from the goal along every path
        south = _closer_terms(env, [2, 2, 2], seed=0)
        assert all(value < 0.0 for value in south), south
    finally:
        env.close()


def test_bad_options_give_one_line_errors() -> None:
    for options, message in (({"along": "curved"}, "one of straight, path"),
                             ({"along": "path", "cell_m": 0}, "cell_m"),
                             ({"along": "path", "clearance_m": -1}, "clearance_m"),
                             ({"cell_m": 0.5}, "only with `along: path`"),
                             ({"along": "path", "radius": 1}, "unknown key")):
        with pytest.raises(ConfigError) as info:
            parse_rewards(Node({"closer_to_goal": {"scale": 10, **options}}, "t.yaml", "task.reward"))
        assert "\n" not in str(info.value) and message in str(info.value), str(info.value)


def test_binary_mode_works_along_the_path() -> None:
    (term,) = parse_rewards(Node({"closer_to_goal": {"scale": 15, "mode": "binary", "along": "path",
                                                     "cell_m": 0.25, "clearance_m": 0.3}},
                                 "t.yaml", "task.reward"))
    assert term.path == PathGrid(cell_m=0.25, clearance_m=0.3)


def test_an_unreachable_goal_is_a_one_line_error(tmp_path: Path) -> None:
    text = TWO_BLOCKS.read_text().replace(
        "  obstacles:\n",
        "  obstacles:\n    - {name: barrier, shape: wall, size: [14, 0.3, 8], position: [0, 7.5, 4]}\n")
    path = tmp_path / "walled_off.yaml"
    path.write_text(text)
    env = make_env(path)
    try:
        with pytest.raises(ConfigError) as info:
            env.reset(seed=0)
    finally:
        env.close()
    text = str(info.value)
    assert "\n" not in text and text.startswith(str(path)) and "'two_blocks'" in text
    assert "cannot be reached" in text
