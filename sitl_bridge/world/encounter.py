"""Encounter families: multi-drone geometry drawn anew every episode from ranges in the YAML.

A `world.encounter:` section replaces `vehicles:` and `goals:`: it names how many drones fly
and one encounter type (`type:`), or several drawn per episode by weight (`mix:`). Every
episode draws a type, then that type's geometry from its ranges (a range is `[low, high]`,
drawn uniformly, or one number), all from the episode's seeded generator (`layout.realize`):
the same seed gives the same geometry. Keys (an example family; each key's default is in
`schema.EncounterType`, overtaking's start_delay_s `schema.OVERTAKING_START_DELAY_S`)::

    encounter:
      drones: 2                      # drone0, drone1, ... each with goal goal0, goal1, ...
      center: [x, y]                 # where the paths meet; default: the workspace's centre
      altitude_m: 2.5                # goal centres' height (use the task's start_altitude_m)
      goal_size: [2, 2, 2]
      lidar: {...}                   # every drone's lidar, as under vehicles[].lidar
      type: head_on                  # one type (its keys beside it), or:
      mix:                           # a type drawn per episode, with probability ~ weight
        - {type: head_on, weight: 1, length_m: [8, 10], lateral_offset_m: [-1, 1]}
        - {type: crossing, angle_deg: [30, 150], length_m: [8, 10]}
        - {type: converging, radius_m: [4, 5], angle_jitter_deg: 10}
        - {type: overtaking, length_m: [6, 8], gap_m: [2, 3], start_delay_s: [3, 5]}
        - {type: bottleneck, distance_m: [2, 6], exit_m: 3, lateral_offset_m: [-2, 2],
           gap_width_m: [1.2, 1.6]}

Every type also takes `heading_deg: [0, 360]` (drone0's direction of travel, ENU degrees
counter-clockwise from east; the whole encounter turns with it) and `start_delay_s: [0, 0]`.

- head_on (2 drones): opposite courses of `length_m`; drone1's path lies `lateral_offset_m` to
  the left of drone0's (negative: right).
- crossing (2 drones): both paths of `length_m` cross at their midpoints at `center`, drone1's
  course `angle_deg` from drone0's, from its left or right (drawn).
- converging (2 or more): drone k starts `radius_m` (drawn per drone) from `center` at bearing
  heading + k * 360/drones + a jitter of +-`angle_jitter_deg`; its goal is the opposite point.
- overtaking (2 drones): one shared course of `length_m`; drone1 (the leader) starts `gap_m`
  ahead of drone0 and waits `start_delay_s` (default [3, 5] s) before it flies, so drone0 catches
  it up (the actions fly one speed: the leader is slow by waiting, not by a slower speed).
- bottleneck (2 or more): a wall across the workspace through `center`, perpendicular to the
  heading, with a full-height gap of `gap_width_m` at `center`. Every drone starts on the
  same side (drawn), `distance_m` from the wall (drawn per drone, so they reach the gap at
  different times) and `lateral_offset_m` along it; its goal lies `exit_m` beyond the wall at
  its own drawn lateral offset. The wall is `wall_height_m` high (default: the workspace's
  top, so nobody flies over it).

Late entries (`start_delay_s`, any type but overtaking): every drone but one, chosen at random,
draws a delay from the range; the one enters at once. A delayed drone is held: it hovers at its
start (the episode starts every drone hovering there) and its actions are ignored until its
delay has passed (`info["entered"]` says when; it is in `env.agents` and scored throughout).

The loader checks every range (low <= high, inside its bounds) and that the largest geometry
of every type fits the workspace around `center` at any heading; each draw keeps spawns
`SPAWN_SEPARATION_M` apart and spawns and goal centres `sense.SPAWN_CLEARANCE_M` clear of obstacles
(redrawn, seeded).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from sitl_bridge.errors import ConfigError, Node
from sitl_bridge.world.schema import (
    ENCOUNTER_TYPES,
    KEYS_OF,
    OVERTAKING_START_DELAY_S,
    Encounter,
    EncounterType,
    LidarConfig,
    Obstacle,
    Opening,
    Shape,
    Vec3,
    Workspace,
)
from sitl_bridge.world.sense import SPAWN_CLEARANCE_M, overlaps

TWO_DRONE_TYPES = ("head_on", "crossing", "overtaking")
SPAWN_SEPARATION_M = 1.5
"""Least horizontal distance between two spawns of one episode (two hovering Iris, margin)."""
SPAWN_Z_M = 0.06
"""Spawns rest on the ground (the episode start lifts every drone to the start altitude)."""
WALL_THICKNESS_M = 0.2
WALL_NAME = "bottleneck_wall"
MAX_DRAWS = 50
"""Draws of one episode's geometry before giving up (a spawn or goal inside an obstacle, or
two spawns too close, each time)."""


@dataclass(frozen=True)
class EncounterDraw:
    """One episode's drawn encounter: per drone its spawn, yaw, goal centre and start delay."""

    kind: str
    spawns_m: tuple[Vec3, ...]
    yaws_rad: tuple[float, ...]
    goal_centers_m: tuple[Vec3, ...]
    start_delays_s: tuple[float, ...]
    wall: Obstacle | None = None


# -- parsing -----------------------------------------------------------------------------------
COMMON_KEYS = {"type", "weight", "heading_deg", "start_delay_s"}
RANGE_BOUNDS = {
    "heading_deg": (-360.0, 360.0), "start_delay_s": (0.0, 600.0), "length_m": (1.0, 1000.0),
    "lateral_offset_m": (-100.0, 100.0), "angle_deg": (5.0, 175.0), "radius_m": (1.0, 500.0),
    "gap_m": (SPAWN_SEPARATION_M, 100.0), "distance_m": (0.5, 500.0), "gap_width_m": (0.6, 100.0),
}
"""Each range key's bounds: crossings between 5 and 175 degrees (0 is overtaking, 180 head-on);
an overtaking gap at least the spawn separation; a gap wider than an Iris (0.55 m)."""


def parse_encounter(node: Node, workspace: Workspace, parse_lidar: Callable[[Node], LidarConfig]) -> Encounter:
    """Parse and check a `world.encounter:` section (`parse_lidar` reads its `lidar:`)."""
    node.mapping()
    if not workspace.min_m[2] <= SPAWN_Z_M:
        raise ConfigError(f"{node.source}: {node.path}: the encounter's spawns rest on the ground (z {SPAWN_Z_M}); "
                          f"world.workspace.min z must be at most that, got {workspace.min_m[2]:g}")
    own = {"drones", "center", "altitude_m", "goal_size", "lidar", "mix"}
    if node.has("mix") and node.has("type"):
        raise node.get("type").error("either type: (one encounter type) or mix: (several), not both")
    if not node.has("mix") and not node.has("type"):
        raise node.error("an encounter with type: (one of " + ", ".join(ENCOUNTER_TYPES) + ") or mix:")
    lo, hi = workspace.min_m, workspace.max_m
    drones = node.get("drones", 2).integer(minimum=2, maximum=16)
    center_node = node.get("center", [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0])
    center = center_node.vector(2)
    altitude = _number(node.get("altitude_m", 2.5), lo[2], hi[2])
    goal_size = node.get("goal_size", [2.0, 2.0, 2.0]).vector(3, positive=True)
    lidar = parse_lidar(node.get("lidar", {}))
    if node.has("mix"):
        node.reject_unknown(own)
        type_nodes = node.get("mix").list(min_len=1)
    else:
        node.reject_unknown(own | COMMON_KEYS | set().union(*KEYS_OF.values()))
        type_nodes = [node]
    types = []
    for t in type_nodes:
        kind = _parse_type(t, drones, own_keys=own if t is node else set())
        types.append(kind)
        _check_fits(kind, t, drones, center, goal_size, workspace)
    return Encounter(drones, center, altitude, goal_size, tuple(types), lidar)  # type: ignore[arg-type]


def _parse_type(node: Node, drones: int, own_keys: set[str]) -> EncounterType:
    node.mapping()
    kind = node.get("type").string(ENCOUNTER_TYPES)
    allowed = COMMON_KEYS | KEYS_OF[kind]
    if not own_keys:
        node.reject_unknown(allowed)
    else:
        for key in sorted(set(node.mapping()) - own_keys - allowed):
            child = node.get(key)
            raise ConfigError(f"{child.source}: {child.path}: a {kind} encounter has no `{key}` "
                              f"(it takes {', '.join(sorted(allowed - {'type'}))})")
    if kind in TWO_DRONE_TYPES and drones != 2:
        raise node.get("type").error(f"a type for {drones} drones ({kind} takes exactly 2; "
                                     "converging and bottleneck take any number)")
    if kind == "overtaking" and not node.has("start_delay_s"):
        start_delay = OVERTAKING_START_DELAY_S
    else:
        start_delay = _range(node, "start_delay_s", (0.0, 0.0))
    defaults = EncounterType(kind)
    values = {key: _range(node, key, getattr(defaults, key)) for key in KEYS_OF[kind]
              if key in RANGE_BOUNDS}
    if "angle_jitter_deg" in KEYS_OF[kind]:
        values["angle_jitter_deg"] = _number(node.get("angle_jitter_deg", 0.0), 0.0, 180.0 / drones)
    if "exit_m" in KEYS_OF[kind]:
        values["exit_m"] = _number(node.get("exit_m", defaults.exit_m), 0.5, 500.0)
    if node.has("wall_height_m"):
        values["wall_height_m"] = _number(node.get("wall_height_m"), 0.5, 1000.0)
    return EncounterType(kind, weight=_number(node.get("weight", 1.0), 0.0, 1e6, positive=True),
                         heading_deg=_range(node, "heading_deg", defaults.heading_deg),
                         start_delay_s=start_delay, **values)


def _range(node: Node, key: str, default: tuple[float, float]) -> tuple[float, float]:
    """`key: [low, high]` (or one number) within the key's bounds, low <= high."""
    low_bound, high_bound = RANGE_BOUNDS[key]
    if not node.has(key):
        return default
    child = node.get(key)
    expected = f"[low, high] with {low_bound:g} <= low <= high <= {high_bound:g} (or one number)"
    if isinstance(child.value, (int, float)) and not isinstance(child.value, bool):
        low = high = float(child.value)
    elif isinstance(child.value, list) and len(child.value) == 2:
        low, high = child.vector(2)
    else:
        raise child.error(expected)
    if not (math.isfinite(low) and math.isfinite(high) and low_bound <= low <= high <= high_bound):
        raise child.error(expected)
    return low, high


def _number(node: Node, minimum: float, maximum: float, *, positive: bool = False) -> float:
    value = node.number(minimum=minimum, maximum=maximum, positive=positive)
    if not math.isfinite(value):
        raise node.error("a finite number")
    return value


def _check_fits(kind: EncounterType, node: Node, drones: int, center: tuple[float, ...],
                goal_size: tuple[float, ...], workspace: Workspace) -> None:
    """The farthest spawn or goal of `kind`, at any heading, plus a goal's half size, must lie
    inside the workspace around the centre."""
    reach = kind.reach_m(drones) + max(goal_size[0], goal_size[1]) / 2.0
    lo, hi = workspace.min_m, workspace.max_m
    room = min(center[0] - lo[0], hi[0] - center[0], center[1] - lo[1], hi[1] - center[1])
    if reach > room:
        raise node.get("type").error(
            f"a geometry that fits the workspace: this {kind.kind} reaches {reach:.2f} m from the centre "
            f"{list(center)} (its largest ranges at any heading, with the goal's half size), "
            f"the workspace {list(lo)}..{list(hi)} only {room:.2f} m")


# -- drawing -----------------------------------------------------------------------------------
def draw_encounter(encounter: Encounter, workspace: Workspace, obstacles: tuple[Obstacle, ...],
                   rng: np.random.Generator, *, source: str = "world") -> EncounterDraw:
    """Draw one episode's encounter from `rng`: the type, then its geometry, the geometry redrawn
    while a spawn or goal lies in an obstacle or two spawns are too close (`MAX_DRAWS` times)."""
    weights = np.array([t.weight for t in encounter.types], dtype=float)
    # the type once (a redraw keeps it: redrawing it too would skew the mix toward easy types)
    kind = encounter.types[int(rng.choice(len(weights), p=weights / weights.sum()))]
    for _ in range(MAX_DRAWS):
        draw = _DRAWERS[kind.kind](kind, encounter, workspace, rng)
        blockers = (*obstacles, *((draw.wall,) if draw.wall else ()))
        points = (*draw.spawns_m, *draw.goal_centers_m)
        clear = not any(o.randomize is None and not o.dynamic and overlaps(o, p, SPAWN_CLEARANCE_M)
                        for o in blockers for p in points)
        apart = all(math.dist(a[:2], b[:2]) >= SPAWN_SEPARATION_M
                    for i, a in enumerate(draw.spawns_m) for b in draw.spawns_m[i + 1:])
        if clear and apart:
            return draw
    raise ConfigError(f"{source}: world.encounter: no {kind.kind} geometry in {MAX_DRAWS} draws kept every spawn and "
                      f"goal clear of the obstacles and spawns {SPAWN_SEPARATION_M} m apart")


def _u(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    low, high = bounds
    return float(low) if high <= low else float(rng.uniform(low, high))


def _point(encounter: Encounter, along: float, left: float, heading: float, z: float) -> Vec3:
    """`center + along * u + left * n`, u the heading's direction, n its left."""
    cx, cy = encounter.center_m
    c, s = math.cos(heading), math.sin(heading)
    return (cx + along * c - left * s, cy + along * s + left * c, z)


def _leg(encounter: Encounter, start: tuple[float, float], end: tuple[float, float],
         heading: float) -> tuple[Vec3, float, Vec3]:
    """Spawn, yaw (toward the goal) and goal centre of a path from `start` to `end`, each given
    as (along, left) in the heading's frame."""
    spawn = _point(encounter, *start, heading, SPAWN_Z_M)
    goal = _point(encounter, *end, heading, encounter.altitude_m)
    return spawn, math.atan2(goal[1] - spawn[1], goal[0] - spawn[0]), goal


def _delays(kind: EncounterType, drones: int, rng: np.random.Generator) -> list[float]:
    """Every drone but one (drawn) waits a drawn delay; that one enters at once."""
    first = int(rng.integers(drones))
    delays = [_u(rng, kind.start_delay_s) for _ in range(drones)]
    delays[first] = 0.0
    return delays


def _finish(kind: EncounterType, legs: list[tuple[Vec3, float, Vec3]], delays: list[float],
            wall: Obstacle | None = None) -> EncounterDraw:
    return EncounterDraw(kind.kind, tuple(leg[0] for leg in legs), tuple(leg[1] for leg in legs),
                         tuple(leg[2] for leg in legs), tuple(delays), wall)


def _head_on(kind: EncounterType, e: Encounter, workspace: Workspace, rng: np.random.Generator) -> EncounterDraw:
    heading = math.radians(_u(rng, kind.heading_deg))
    half = _u(rng, kind.length_m) / 2.0
    offset = _u(rng, kind.lateral_offset_m)
    legs = [_leg(e, (-half, 0.0), (half, 0.0), heading), _leg(e, (half, offset), (-half, offset), heading)]
    return _finish(kind, legs, _delays(kind, e.drones, rng))


def _crossing(kind: EncounterType, e: Encounter, workspace: Workspace, rng: np.random.Generator) -> EncounterDraw:
    heading = math.radians(_u(rng, kind.heading_deg))
    half = _u(rng, kind.length_m) / 2.0
    angle = math.radians(_u(rng, kind.angle_deg)) * (1.0 if rng.random() < 0.5 else -1.0)
    legs = [_leg(e, (-half, 0.0), (half, 0.0), heading), _leg(e, (-half, 0.0), (half, 0.0), heading + angle)]
    return _finish(kind, legs, _delays(kind, e.drones, rng))


def _converging(kind: EncounterType, e: Encounter, workspace: Workspace, rng: np.random.Generator) -> EncounterDraw:
    heading = math.radians(_u(rng, kind.heading_deg))
    legs = []
    for k in range(e.drones):
        radius = _u(rng, kind.radius_m)
        jitter = _u(rng, (-kind.angle_jitter_deg, kind.angle_jitter_deg))
        bearing = heading + 2.0 * math.pi * k / e.drones + math.radians(jitter)
        legs.append(_leg(e, (radius, 0.0), (-radius, 0.0), bearing))
    return _finish(kind, legs, _delays(kind, e.drones, rng))


def _overtaking(kind: EncounterType, e: Encounter, workspace: Workspace, rng: np.random.Generator) -> EncounterDraw:
    heading = math.radians(_u(rng, kind.heading_deg))
    length, gap = _u(rng, kind.length_m), _u(rng, kind.gap_m)
    back = -(length + gap) / 2.0
    legs = [_leg(e, (back, 0.0), (back + length, 0.0), heading),
            _leg(e, (back + gap, 0.0), (back + gap + length, 0.0), heading)]
    return _finish(kind, legs, [0.0, _u(rng, kind.start_delay_s)])


def _bottleneck(kind: EncounterType, e: Encounter, workspace: Workspace, rng: np.random.Generator) -> EncounterDraw:
    heading = math.radians(_u(rng, kind.heading_deg))
    side = 1.0 if rng.random() < 0.5 else -1.0  # which side of the wall every drone starts on
    legs = [_leg(e, (-side * _u(rng, kind.distance_m), _u(rng, kind.lateral_offset_m)),
                 (side * kind.exit_m, _u(rng, kind.lateral_offset_m)), heading) for _ in range(e.drones)]
    gap = _u(rng, kind.gap_width_m)
    lo, hi = workspace.min_m, workspace.max_m
    cx, cy = e.center_m
    # long enough to cross the workspace from the centre at any heading: no way round it
    length = 2.0 * max(math.hypot(x - cx, y - cy) for x in (lo[0], hi[0]) for y in (lo[1], hi[1])) + 1.0
    height = kind.wall_height_m if kind.wall_height_m is not None else hi[2]
    shape = Shape("wall", size_m=(length, WALL_THICKNESS_M, height),
                  opening=Opening(offset_m=0.0, bottom_m=0.0, width_m=gap, height_m=height))
    # the wall's own x runs along it: perpendicular to the heading
    wall = Obstacle(WALL_NAME, shape, (cx, cy, height / 2.0), heading + math.pi / 2.0,
                    color_rgba=(0.6, 0.6, 0.6, 1.0))
    return _finish(kind, legs, _delays(kind, e.drones, rng), wall)


_DRAWERS = {"head_on": _head_on, "crossing": _crossing, "converging": _converging,
            "overtaking": _overtaking, "bottleneck": _bottleneck}
