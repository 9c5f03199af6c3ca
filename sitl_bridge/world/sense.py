"""Geometry sense checks of a parsed world: mistakes that parse but cannot make a scenario.

A goal that lies entirely outside the workspace can never be reached; an obstacle placed on a
spawn point makes the take-off fail much later with a message that names no obstacle. Both are
reported at load time, naming the key, like every other `ConfigError`.
"""

from __future__ import annotations

import math

from sitl_bridge.errors import ConfigError, Node
from sitl_bridge.world.schema import Obstacle, Vec3, World

SPAWN_CLEARANCE_M = 0.35
"""Free space a spawn point needs around it: the Iris's arm (0.25 m) plus a margin."""


def check_world_sense(world: World, node: Node) -> None:
    """Raise a one-line `ConfigError` for goals outside the workspace or obstacles on spawns
    (`node` is the `world:` section the world was parsed from)."""
    lo, hi = world.workspace.min_m, world.workspace.max_m
    for i, goal in enumerate(world.goals):
        # The box the goal can cover: its centre, or the range a randomised centre is drawn from.
        centre_low = goal.randomize_min_m or goal.center_m
        centre_high = goal.randomize_max_m or goal.center_m
        low = [c - s / 2.0 for c, s in zip(centre_low, goal.size_m, strict=True)]
        high = [c + s / 2.0 for c, s in zip(centre_high, goal.size_m, strict=True)]
        if any(top < w_low or bottom > w_high
               for bottom, top, w_low, w_high in zip(low, high, lo, hi, strict=True)):
            key = "randomize" if goal.randomize_min_m is not None else "center"
            raise node.get("goals").list()[i].get(key).error(
                f"a goal box overlapping the workspace {list(lo)}..{list(hi)} (size {list(goal.size_m)})")
    for k, obstacle in enumerate(world.obstacles):
        if obstacle.dynamic or obstacle.randomize is not None:
            continue  # placed per episode or moving: nothing fixed to check
        for v, vehicle in enumerate(world.vehicles):
            if overlaps(obstacle, vehicle.spawn.position_m, SPAWN_CLEARANCE_M):
                where = node.get("obstacles").list()[k]
                raise ConfigError(
                    f"{where.source}: {where.path}: obstacle '{obstacle.name}' covers the spawn point "
                    f"{list(vehicle.spawn.position_m)} of vehicle '{vehicle.name}' (world.vehicles[{v}]); "
                    f"move one of them (a spawn needs {SPAWN_CLEARANCE_M} m of free space)")


def overlaps(obstacle: Obstacle, point: Vec3, margin_m: float) -> bool:
    """True when `point` lies within `margin_m` of the obstacle's shape at its nominal pose."""
    dx, dy, dz = (p - c for p, c in zip(point, obstacle.position_m, strict=True))
    # Into the obstacle's frame (yaw about z, counter-clockwise).
    c, s = math.cos(obstacle.yaw_rad), math.sin(obstacle.yaw_rad)
    x, y = c * dx + s * dy, -s * dx + c * dy
    shape = obstacle.shape
    if shape.kind == "sphere":
        return math.sqrt(x * x + y * y + dz * dz) <= (shape.radius_m or 0.0) + margin_m
    if shape.kind == "cylinder":
        return (math.hypot(x, y) <= (shape.radius_m or 0.0) + margin_m
                and abs(dz) <= (shape.height_m or 0.0) / 2.0 + margin_m)
    boxes = shape.wall_boxes() if shape.kind == "wall" else [
        (tuple(v / 2.0 for v in shape.size_m or (0.0, 0.0, 0.0)), (0.0, 0.0, 0.0))]
    return any(all(abs(p - o) <= h + margin_m for p, o, h in zip((x, y, dz), offset, half, strict=True))
               for half, offset in boxes)
