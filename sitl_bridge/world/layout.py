"""One episode's concrete layout of a world: randomised spawns, goals and obstacles drawn.

`realize(world, rng)` is pure (no pybullet) so envs, tests and the simulator agree on what was
drawn. Draw order is fixed (goals, spawns, obstacles; or under `world.encounter` the encounter,
then obstacles) so a seed fixes the whole layout.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sitl_bridge.world.encounter import draw_encounter
from sitl_bridge.world.schema import Obstacle, Shape, Vec3, World


@dataclass(frozen=True)
class GoalPlacement:
    """A goal region as placed this episode (ENU, m)."""

    name: str
    center_m: Vec3
    size_m: Vec3

    def contains(self, position_enu_m) -> bool:
        """True when the point lies inside the goal box."""
        return all(abs(float(p) - c) <= s / 2.0 for p, c, s in zip(position_enu_m, self.center_m, self.size_m, strict=True))

    def distance_m(self, position_enu_m) -> float:
        """Euclidean distance from the point to the goal's centre."""
        return math.dist([float(p) for p in position_enu_m], self.center_m)


@dataclass(frozen=True)
class ObstaclePlacement:
    """An obstacle as placed this episode: shape chosen, pose drawn (ENU, m, rad)."""

    name: str
    shape: Shape
    position_m: Vec3
    yaw_rad: float
    spec: Obstacle


@dataclass(frozen=True)
class Layout:
    """Everything randomised in one episode."""

    spawn_positions_m: tuple[Vec3, ...]
    spawn_yaws_rad: tuple[float, ...]        # ENU yaw
    goals: tuple[GoalPlacement, ...]
    vehicle_goals: tuple[int | None, ...]    # per vehicle, index into goals
    obstacles: tuple[ObstaclePlacement, ...]
    start_delays_s: tuple[float, ...] = ()
    """Per vehicle: simulated seconds it is held hovering before its actions fly (empty: none)."""
    encounter: str | None = None
    """The encounter type drawn this episode (`world.encounter`), else None."""

    def goal_of(self, vehicle: int) -> GoalPlacement | None:
        """The goal region of a vehicle this episode (None when the vehicle has no goal)."""
        index = self.vehicle_goals[vehicle]
        return None if index is None else self.goals[index]


def _uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(lo) if hi <= lo else float(rng.uniform(lo, hi))


def realize(world: World, rng: np.random.Generator) -> Layout:
    """Draw one episode's layout of `world` from `rng`."""
    if world.encounter is not None:
        return _realize_encounter(world, rng)
    goals = []
    for g in world.goals:
        center = g.center_m
        if g.randomize_min_m is not None and g.randomize_max_m is not None:
            center = tuple(_uniform(rng, lo, hi) for lo, hi in zip(g.randomize_min_m, g.randomize_max_m, strict=True))
        goals.append(GoalPlacement(g.name, center, g.size_m))  # type: ignore[arg-type]

    spawns: list[Vec3] = []
    yaws: list[float] = []
    for v in world.vehicles:
        s = v.spawn
        pos = tuple(p + _uniform(rng, -r, r) for p, r in zip(s.position_m, s.randomize_position_m, strict=True))
        spawns.append(pos)  # type: ignore[arg-type]
        yaws.append(s.yaw_rad + _uniform(rng, -s.randomize_yaw_rad, s.randomize_yaw_rad))

    vehicle_goals = tuple(v.goal for v in world.vehicles)
    obstacles = [_placed(o, rng, spawns, goals, vehicle_goals) for o in world.obstacles]
    return Layout(tuple(spawns), tuple(yaws), tuple(goals), vehicle_goals, tuple(obstacles))


def _realize_encounter(world: World, rng: np.random.Generator) -> Layout:
    """The encounter's drawn spawns and goals, then the obstacles (plus a bottleneck's wall)."""
    assert world.encounter is not None
    draw = draw_encounter(world.encounter, world.workspace, world.obstacles, rng, source=world.source)
    goals = [GoalPlacement(g.name, center, g.size_m) for g, center in zip(world.goals, draw.goal_centers_m, strict=True)]
    spawns = list(draw.spawns_m)
    vehicle_goals = tuple(v.goal for v in world.vehicles)
    obstacles = [_placed(o, rng, spawns, goals, vehicle_goals) for o in world.obstacles]
    if draw.wall is not None:
        obstacles.append(ObstaclePlacement(draw.wall.name, draw.wall.shape, draw.wall.position_m,
                                           draw.wall.yaw_rad, draw.wall))
    return Layout(tuple(spawns), draw.yaws_rad, tuple(goals), vehicle_goals, tuple(obstacles),
                  draw.start_delays_s, draw.kind)


def _placed(o: Obstacle, rng: np.random.Generator, spawns: list[Vec3], goals: list[GoalPlacement],
            vehicle_goals: tuple[int | None, ...]) -> ObstaclePlacement:
    """An obstacle placed for this episode; a randomised one redrawn off spawns and goals."""
    placement = _place_obstacle(o, rng, spawns, goals, vehicle_goals)
    if o.randomize is not None:
        # a randomised obstacle must neither bury a spawn nor fill a goal: redraw (seeded)
        for _ in range(MAX_REDRAWS):
            if _clear_of(placement, spawns, goals):
                break
            placement = _place_obstacle(o, rng, spawns, goals, vehicle_goals)
    return placement


#: Redraws of a randomised obstacle that lands on a spawn or a goal before giving up (keeping it).
MAX_REDRAWS = 50
#: Horizontal clearance (m) kept between a randomised obstacle and spawns / goal centres.
CLEARANCE_M = 0.5


def _place_obstacle(o: Obstacle, rng: np.random.Generator, spawns: list[Vec3], goals: list[GoalPlacement],
                    vehicle_goals: tuple[int | None, ...]) -> ObstaclePlacement:
    shape, position, yaw = o.shape, o.position_m, o.yaw_rad
    r = o.randomize
    if r is not None:
        if r.variants:
            shape = r.variants[int(rng.integers(len(r.variants)))]
        if r.along_path is not None:
            a = r.along_path
            start = spawns[a.vehicle]
            goal_index = vehicle_goals[a.vehicle]
            assert goal_index is not None  # checked by the loader
            end = goals[goal_index].center_m
            t = _uniform(rng, a.fraction[0], a.fraction[1])
            dx, dy = end[0] - start[0], end[1] - start[1]
            norm = math.hypot(dx, dy) or 1.0
            side = _uniform(rng, -a.lateral_m, a.lateral_m)
            # perpendicular (left of the path) offset, horizontal; resting on the ground
            position = (start[0] + t * dx - side * dy / norm, start[1] + t * dy + side * dx / norm,
                        shape.half_height_m)
        position = tuple(p + _uniform(rng, -d, d) for p, d in zip(position, r.position_m, strict=True))  # type: ignore[assignment]
        yaw = yaw + _uniform(rng, -r.yaw_rad, r.yaw_rad)
    return ObstaclePlacement(o.name, shape, position, yaw, o)


def horizontal_radius_m(shape: Shape) -> float:
    """Radius of a vertical cylinder around the shape's centre that contains it."""
    if shape.kind in ("sphere", "cylinder"):
        return shape.radius_m or 0.0
    sx, sy, _ = shape.size_m or (0.0, 0.0, 0.0)
    return 0.5 * math.hypot(sx, sy)


def _clear_of(placement: ObstaclePlacement, spawns: list[Vec3], goals: list[GoalPlacement]) -> bool:
    reach = horizontal_radius_m(placement.shape) + CLEARANCE_M
    x, y, _ = placement.position_m
    points = [s[:2] for s in spawns] + [g.center_m[:2] for g in goals]
    return all(math.hypot(px - x, py - y) > reach for px, py in points)
