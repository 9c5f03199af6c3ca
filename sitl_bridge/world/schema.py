"""World schema: typed, immutable description of a scenario's physical world.

Units and frames (also stated at the top of every `worlds/*.yaml`): positions and sizes in
metres in the world ENU frame (x east, y north, z up, origin on the ground at the home
position); yaw in degrees in the YAML (counter-clockwise from east, ENU) and radians here;
speeds in m/s. The scenario's other top-level sections (`task:` for the envs, `train:` for the
trainer) are kept raw as `errors.Node` so their owners validate them.

The `world:` section, every key (optional ones show their default)::

    world:
      name: window                       # required
      description: ""
      home: {lat: 47.397742, lon: 8.545594, alt: 488.0, magnetic_year: 2025.5}
      physics: {step_us: 4000, gravity: 9.8066, solver_iterations: 20,
                hard_ground_speed: 2.0, crash_tilt: 60}   # ground contact faster / more tilted = crash
      workspace: {min: [x, y, z], max: [x, y, z]}          # required; vehicles must stay inside
      ground: true                       # infinite plane at z = 0
      vehicles:                          # required, at least one
        - name: drone0
          model: iris                    # the only model
          spawn: {position: [x, y, z], yaw: 90,            # body centre; z 0.06 rests on the ground
                  randomize: {position: [dx, dy, dz], yaw: 10}}   # uniform +- per episode
          goal: exit                     # name of a goal below
          lidar: {horizontal: {rays: 35, fov: 360}, up: {rays: 6, fov: 90}, down: {rays: 6, fov: 90},
                  range: 5.0, near: 1.0, crash: 0.4, filter_window: 1, flags: [horizontal, up]}
      goals:
        - {name: exit, center: [x, y, z], size: [sx, sy, sz],
           randomize: {min: [x, y, z], max: [x, y, z]}}    # centre drawn uniformly per episode
      obstacles:
        - name: block                    # unique; reported in collisions
          shape: box                     # box | cylinder | sphere | wall | mesh
          size: [sx, sy, sz]             # box; wall: [length, thickness, height]; mesh: bounding box
          radius: 0.5                    # cylinder, sphere
          height: 2.0                    # cylinder
          opening: {offset: 0, bottom: 1.8, width: 1.5, height: 1.2}   # wall only: a window
          file: house.obj                # mesh only, relative to the YAML file
          scale: [1, 1, 1]               # mesh only
          position: [x, y, z]            # centre of the shape
          yaw: 0
          color: [r, g, b, a]
          mass: 1.0                      # moving obstacles only
          mover: {type: patrol, speed: 1.4, points: [[x, y, z], [x, y, z]],
                  random_start: false}   # true: each episode starts at a uniformly drawn point
                                         # of the out-and-back route (seeded), not at points[0]
          # or:
          mover: {type: random_legs, speed: 8, min: [x, y, z], max: [x, y, z]}
          randomize:                     # static obstacles only, per episode
            along_path: {vehicle: drone0, fraction: [0.35, 0.65], lateral: 0.5}  # on spawn->goal line
            position: [dx, dy, dz]       # uniform +- offset
            yaw: 30                      # uniform +- degrees
            variants: [{shape: box, size: [1, 1, 3]}, {shape: cylinder, radius: 0.5, height: 3}]
      encounter:                         # instead of vehicles: and goals: a multi-drone encounter
        drones: 2                        # family drawn anew every episode; its keys and types:
        type: crossing                   # sitl_bridge/world/encounter.py (docs/scenarios.md)
        angle_deg: [30, 150]
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from sitl_bridge.errors import Node

Vec3 = tuple[float, float, float]

SHAPE_KINDS = ("box", "cylinder", "sphere", "wall", "mesh")


@dataclass(frozen=True)
class GeoHome:
    """Geodetic position of the ENU origin (Gazebo's default home unless the world says otherwise)."""

    lat_deg: float = 47.397742
    lon_deg: float = 8.545594
    alt_m: float = 488.0
    #: Decimal year for the World Magnetic Model lookup of the magnetometer field.
    magnetic_year: float = 2025.5


@dataclass(frozen=True)
class Opening:
    """Rectangular hole in a wall, in the wall's own frame (x along the wall, z up from its base)."""

    offset_m: float  # centre of the opening along the wall, from the wall's centre
    bottom_m: float  # height of the opening's lower edge above the wall's base
    width_m: float
    height_m: float


@dataclass(frozen=True)
class Shape:
    """One obstacle's collision geometry, centred on its position.

    box: `size_m` = full extents (x, y, z). cylinder: `radius_m`, `height_m` (axis up).
    sphere: `radius_m`. wall: `size_m` = (length along x, thickness along y, height) plus an
    optional `opening`. mesh: `mesh_file` (absolute path) scaled by `mesh_scale`.
    """

    kind: str
    size_m: Vec3 | None = None
    radius_m: float | None = None
    height_m: float | None = None
    opening: Opening | None = None
    mesh_file: str | None = None
    mesh_scale: Vec3 = (1.0, 1.0, 1.0)

    @property
    def half_height_m(self) -> float:
        """Half of the vertical extent (resting on the ground means centre z = this)."""
        if self.kind in ("box", "wall", "mesh") and self.size_m is not None:
            return self.size_m[2] / 2.0
        if self.kind == "cylinder":
            return (self.height_m or 0.0) / 2.0
        if self.kind == "sphere":
            return self.radius_m or 0.0
        return 0.0

    def wall_boxes(self) -> list[tuple[Vec3, Vec3]]:
        """A wall as boxes around its opening: list of (half_extents_m, centre_offset_m)."""
        assert self.kind == "wall" and self.size_m is not None
        length, thickness, height = self.size_m
        t = thickness / 2.0
        if self.opening is None:
            return [((length / 2.0, t, height / 2.0), (0.0, 0.0, 0.0))]
        o = self.opening
        x0, x1 = -length / 2.0, length / 2.0
        z0, z1 = -height / 2.0, height / 2.0
        ox0, ox1 = o.offset_m - o.width_m / 2.0, o.offset_m + o.width_m / 2.0
        oz0, oz1 = z0 + o.bottom_m, z0 + o.bottom_m + o.height_m
        boxes: list[tuple[Vec3, Vec3]] = []

        def add(ax0: float, ax1: float, az0: float, az1: float) -> None:
            if ax1 - ax0 > 1e-9 and az1 - az0 > 1e-9:
                boxes.append((((ax1 - ax0) / 2.0, t, (az1 - az0) / 2.0),
                              ((ax0 + ax1) / 2.0, 0.0, (az0 + az1) / 2.0)))

        add(x0, ox0, z0, z1)      # left of the opening, full height
        add(ox1, x1, z0, z1)      # right of the opening, full height
        add(ox0, ox1, z0, oz0)    # below the opening
        add(ox0, ox1, oz1, z1)    # above the opening
        return boxes


@dataclass(frozen=True)
class PatrolMover:
    """Walks back and forth along a polyline at constant speed (a pedestrian).

    With `random_start` each episode starts at a uniformly drawn distance along the out-and-back
    route (drawn from the episode's seeded mover stream), so a policy cannot learn the timing of
    a walker from the clock; without it every episode starts at the first point.
    """

    points_m: tuple[Vec3, ...]
    speed_m_s: float
    random_start: bool = False


@dataclass(frozen=True)
class RandomLegsMover:
    """Flies straight legs to uniformly random points inside a cuboid (a bird); seeded."""

    min_m: Vec3
    max_m: Vec3
    speed_m_s: float


Mover = PatrolMover | RandomLegsMover


@dataclass(frozen=True)
class AlongPath:
    """Place an obstacle on the straight line from a vehicle's spawn to its goal."""

    vehicle: int                    # index into World.vehicles
    fraction: tuple[float, float]   # uniform range along the line (0 = spawn, 1 = goal)
    lateral_m: float = 0.0          # uniform +- offset perpendicular to the line (horizontal)


@dataclass(frozen=True)
class ObstacleRandomization:
    """Per-episode randomisation of a static obstacle.

    `along_path` overrides x, y (z: resting on the ground); `position_m` adds a uniform +-
    offset per axis; `variants` replaces the shape by one of these, uniformly.
    """

    along_path: AlongPath | None = None
    position_m: Vec3 = (0.0, 0.0, 0.0)
    yaw_rad: float = 0.0
    variants: tuple[Shape, ...] = ()


@dataclass(frozen=True)
class Obstacle:
    """A static or moving obstacle. Moving ones have a mover, no gravity, and are not static."""

    name: str
    shape: Shape
    position_m: Vec3
    yaw_rad: float = 0.0
    color_rgba: tuple[float, float, float, float] = (0.6, 0.6, 0.6, 1.0)
    mover: Mover | None = None
    mass_kg: float = 1.0   # moving obstacles only (static ones have mass 0)
    randomize: ObstacleRandomization | None = None

    @property
    def dynamic(self) -> bool:
        return self.mover is not None


@dataclass(frozen=True)
class GoalRegion:
    """An axis-aligned box the vehicle must reach; optionally re-drawn every episode."""

    name: str
    center_m: Vec3
    size_m: Vec3
    randomize_min_m: Vec3 | None = None  # centre drawn uniformly in [min, max] when set
    randomize_max_m: Vec3 | None = None


@dataclass(frozen=True)
class Spawn:
    """Where a vehicle starts (its body centre) and its ENU yaw, with optional +- randomisation."""

    position_m: Vec3
    yaw_rad: float = 0.0
    randomize_position_m: Vec3 = (0.0, 0.0, 0.0)
    randomize_yaw_rad: float = 0.0


@dataclass(frozen=True)
class LidarConfig:
    """Lidar layout of one vehicle (body-fixed rays from the body centre).

    horizontal: `horizontal_rays` evenly over `horizontal_fov_deg` in the body x-y plane, centred on
    forward, counter-clockwise (FLU). up/down: fans in the body x-z plane centred on straight up /
    down, spanning `up_fov_deg` / `down_fov_deg` from forward to back. `near`/`crash` flags and
    `min_m` look at the ray groups in `flag_groups`.
    """

    horizontal_rays: int = 35
    horizontal_fov_deg: float = 360.0
    up_rays: int = 6
    up_fov_deg: float = 90.0
    down_rays: int = 6
    down_fov_deg: float = 90.0
    range_m: float = 5.0
    near_m: float = 1.0
    crash_m: float = 0.4
    filter_window: int = 1          # moving average over this many scans; 1 = off
    flag_groups: tuple[str, ...] = ("horizontal", "up")


@dataclass(frozen=True)
class VehicleSpec:
    """One vehicle of the world."""

    name: str
    model: str
    spawn: Spawn
    goal: int | None = None          # index into World.goals
    lidar: LidarConfig = field(default_factory=LidarConfig)


@dataclass(frozen=True)
class Workspace:
    """Axis-aligned box the vehicles must stay in (ENU, m)."""

    min_m: Vec3
    max_m: Vec3

    def contains(self, position_enu_m) -> bool:
        x, y, z = (float(c) for c in position_enu_m)
        lo, hi = self.min_m, self.max_m
        return lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1] and lo[2] <= z <= hi[2]


@dataclass(frozen=True)
class PhysicsSettings:
    """Simulation settings of a world."""

    step_us: int = 4000
    gravity_m_s2: float = 9.8066
    solver_iterations: int = 20
    #: Ground contact faster than this (m/s), or while tilted beyond `crash_tilt_deg`, is a crash.
    hard_ground_speed_m_s: float = 2.0
    crash_tilt_deg: float = 60.0


ENCOUNTER_TYPES = ("head_on", "crossing", "converging", "overtaking", "bottleneck")
"""`world.encounter` types (their geometry, keys and draws: `sitl_bridge/world/encounter.py`)."""
KEYS_OF = {
    "head_on": {"length_m", "lateral_offset_m"},
    "crossing": {"length_m", "angle_deg"},
    "converging": {"radius_m", "angle_jitter_deg"},
    "overtaking": {"length_m", "gap_m"},
    "bottleneck": {"distance_m", "exit_m", "lateral_offset_m", "gap_width_m", "wall_height_m"},
}
"""Each encounter type's own keys (besides type, weight, heading_deg, start_delay_s)."""


OVERTAKING_START_DELAY_S = (3.0, 5.0)
"""An overtaking's default `start_delay_s` (the leader's wait; every other type's is none)."""


@dataclass(frozen=True)
class EncounterType:
    """One encounter type's ranges (metres, seconds; angles in degrees as written)."""

    kind: str
    weight: float = 1.0
    heading_deg: tuple[float, float] = (0.0, 360.0)
    start_delay_s: tuple[float, float] = (0.0, 0.0)
    length_m: tuple[float, float] = (8.0, 10.0)
    lateral_offset_m: tuple[float, float] = (0.0, 0.0)
    angle_deg: tuple[float, float] = (90.0, 90.0)
    radius_m: tuple[float, float] = (4.0, 5.0)
    angle_jitter_deg: float = 0.0
    gap_m: tuple[float, float] = (2.0, 3.0)
    distance_m: tuple[float, float] = (2.0, 6.0)
    exit_m: float = 3.0
    gap_width_m: tuple[float, float] = (1.2, 1.6)
    wall_height_m: float | None = None

    def describe(self) -> str:
        """One line: the type and its ranges as written (degrees, metres, seconds)."""
        keys = ["heading_deg", *sorted(KEYS_OF[self.kind] - {"wall_height_m"}), "start_delay_s"]

        def shown(value: object) -> str:
            if isinstance(value, tuple):
                low, high = value
                return f"{low:g}" if low == high else f"{low:g}..{high:g}"
            return f"{value:g}"  # type: ignore[str-format]

        return f"`{self.kind}`: " + ", ".join(f"{key} {shown(getattr(self, key))}" for key in keys)

    def reach_m(self, drones: int) -> float:
        """The farthest any spawn or goal of this type can lie from the centre (horizontal)."""
        if self.kind == "head_on":
            return math.hypot(self.length_m[1] / 2.0, max(abs(v) for v in self.lateral_offset_m))
        if self.kind == "crossing":
            return self.length_m[1] / 2.0
        if self.kind == "converging":
            return self.radius_m[1]
        if self.kind == "overtaking":
            return (self.length_m[1] + self.gap_m[1]) / 2.0
        lateral = max(abs(v) for v in self.lateral_offset_m)
        return math.hypot(max(self.distance_m[1], self.exit_m), lateral)


@dataclass(frozen=True)
class Encounter:
    """A world's encounter family: the drones, where they meet, and the types drawn."""

    drones: int
    center_m: tuple[float, float]
    altitude_m: float
    goal_size_m: Vec3
    types: tuple[EncounterType, ...]
    lidar: LidarConfig = field(default_factory=LidarConfig)

    def describe(self) -> list[str]:
        """Markdown lines: each type with its probability and ranges, and what a delay does."""
        total = sum(t.weight for t in self.types)
        lines = [f"{self.drones} drones; every episode draws one type (probability), then its geometry "
                 f"around ({self.center_m[0]:g}, {self.center_m[1]:g}), goals {self.altitude_m:g} m up "
                 "(`sitl_bridge/world/encounter.py`):", ""]
        lines += [f"- {t.weight / total:.0%} {t.describe()}" for t in self.types]
        if any(t.start_delay_s[1] > 0.0 for t in self.types):
            lines += ["", "A drone with a start delay is held hovering at its start, its actions ignored, "
                      "until the delay has passed (`info[\"entered\"]` is False while its next action "
                      "would be ignored); it is in `env.agents` and scored throughout."]
        return lines



@dataclass(frozen=True)
class World:
    """A loaded, validated world (`world:` section) plus the raw `task:` / `train:` sections."""

    name: str
    source: str
    description: str = ""
    home: GeoHome = field(default_factory=GeoHome)
    physics: PhysicsSettings = field(default_factory=PhysicsSettings)
    workspace: Workspace = field(default_factory=lambda: Workspace((-50.0, -50.0, 0.0), (50.0, 50.0, 30.0)))
    ground: bool = True
    vehicles: tuple[VehicleSpec, ...] = ()
    goals: tuple[GoalRegion, ...] = ()
    obstacles: tuple[Obstacle, ...] = ()
    encounter: Encounter | None = None
    """Drawn anew every episode: the vehicles' spawns and goals (their own are episode 0's)."""
    task: Node | None = None
    train: Node | None = None

    @property
    def num_vehicles(self) -> int:
        return len(self.vehicles)

    def vehicle_index(self, name: str) -> int:
        """Index of the vehicle called `name` (KeyError if none)."""
        for i, v in enumerate(self.vehicles):
            if v.name == name:
                return i
        raise KeyError(name)

    def summary(self) -> str:
        """One line: name, vehicles, obstacles (static/moving), goals, randomised parts."""
        moving = sum(1 for o in self.obstacles if o.dynamic)
        randomised = []
        if self.encounter is not None:
            randomised.append("encounter (" + ", ".join(t.kind for t in self.encounter.types) + ")")
        elif any(g.randomize_min_m is not None for g in self.goals):
            randomised.append("goal")
        if any(v.spawn.randomize_position_m != (0.0, 0.0, 0.0) or v.spawn.randomize_yaw_rad for v in self.vehicles):
            randomised.append("spawn")
        if any(o.randomize is not None for o in self.obstacles):
            randomised.append("obstacle")
        lo, hi = self.workspace.min_m, self.workspace.max_m
        size = "x".join(f"{high - low:g}" for low, high in zip(lo, hi, strict=True))
        return (
            f"{self.name}: {self.num_vehicles} vehicle(s), {len(self.obstacles) - moving} static + "
            f"{moving} moving obstacle(s), {len(self.goals)} goal(s), workspace {size} m, "
            f"randomised: {', '.join(randomised) or 'nothing'}"
        )


def deg(value: float) -> float:
    """Degrees -> radians (YAML angles are degrees)."""
    return math.radians(value)
