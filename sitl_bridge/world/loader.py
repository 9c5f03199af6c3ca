"""Read a scenario YAML file into a validated `World`.

A scenario file has a required `world:` mapping (parsed here), and optional `task:` and
`train:` mappings owned by the envs and the trainer (kept raw as `Node`s). Any other top-level
key is an error. Every error is a one-line `ConfigError` naming file, key path and expectation.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from sitl_bridge.errors import NAME_MAX_CHARS, ConfigError, Node, load_yaml
from sitl_bridge.world.clock import divides
from sitl_bridge.world.encounter import draw_encounter, parse_encounter
from sitl_bridge.world.lookup import world_file
from sitl_bridge.world.schema import (
    SHAPE_KINDS,
    AlongPath,
    GeoHome,
    GoalRegion,
    LidarConfig,
    Obstacle,
    ObstacleRandomization,
    Opening,
    PatrolMover,
    PhysicsSettings,
    RandomLegsMover,
    Shape,
    Spawn,
    VehicleSpec,
    Workspace,
    World,
)
from sitl_bridge.world.sense import check_world_sense

TOP_LEVEL_KEYS = frozenset({"world", "task", "train"})
VEHICLE_MODELS = ("iris",)
LIDAR_GROUPS = ("horizontal", "up", "down")


def load_world(path: str | Path) -> World:
    """Load and validate a scenario file (a path, or a shipped world's bare name); raises
    `ConfigError` with a one-line message."""
    path = world_file(path)
    root = load_yaml(path)
    return parse_scenario(root, base_dir=Path(path).parent)


def parse_scenario(root: Node, base_dir: Path = Path(".")) -> World:
    """Build a `World` from an already-read root node (see `load_world`)."""
    if root.value is None:
        raise ConfigError(f"{root.source}: empty file (expected a mapping with a `world:` key)")
    root.mapping()
    root.reject_unknown(TOP_LEVEL_KEYS)
    task = root.get("task") if root.has("task") else None
    train = root.get("train") if root.has("train") else None
    if task is not None:
        task.mapping()
    if train is not None:
        train.mapping()
    world = _parse_world(root.get("world"), base_dir, task, train)
    if task is not None:
        _check_step_divides_task(root.get("world").get("physics", {}), world.physics.step_us, task)
    return world


TASK_SPANS_S = (("action", "duration_s", 1.0), ("action", "zero_velocity_s", 0.0))
"""The task's spans of simulated time (section, key, default: envs/task.py `ActionConfig`),
each flown as whole physics steps by every backend."""


def _check_step_divides_task(physics: Node, step_us: int, task: Node) -> None:
    """`physics.step_us` must divide every span of the task (see `world.clock`), else the
    backends could not fly the same steps."""
    for section, key, default in TASK_SPANS_S:
        node = task.get(section, {})
        value = node.get(key, default).value if isinstance(node.value, dict) else default
        if isinstance(value, (int, float)) and not isinstance(value, bool) and value > 0 \
                and not divides(step_us, value):
            raise physics.get("step_us", step_us).error(
                f"a step in microseconds that divides task.{section}.{key} ({value:g} s)", step_us)


# ---------------------------------------------------------------------------------------------
def _parse_world(node: Node, base_dir: Path, task: Node | None, train: Node | None) -> World:
    node.mapping()
    node.reject_unknown({"name", "description", "home", "physics", "workspace", "ground",
                         "vehicles", "goals", "obstacles", "encounter"})
    name = node.get("name").string(max_chars=NAME_MAX_CHARS)
    description = node.get("description", "").string()
    home = _parse_home(node.get("home", {}))
    physics = _parse_physics(node.get("physics", {}))
    workspace = _parse_box(node.get("workspace"), "workspace")
    ground = node.get("ground", True).boolean()
    if node.has("encounter"):
        return _parse_encounter_world(node, base_dir, task, train, name=name, description=description,
                                      home=home, physics=physics, workspace=workspace, ground=ground)

    goal_nodes = node.get("goals", []).list()
    goals = tuple(_parse_goal(g) for g in goal_nodes)
    _unique([g.name for g in goals], goal_nodes)
    goal_index = {g.name: i for i, g in enumerate(goals)}

    vehicle_nodes = node.get("vehicles").list(min_len=1)
    vehicles = tuple(_parse_vehicle(v, goal_index) for v in vehicle_nodes)
    _unique([v.name for v in vehicles], vehicle_nodes)
    vehicle_index = {v.name: i for i, v in enumerate(vehicles)}
    for v, vnode in zip(vehicles, vehicle_nodes, strict=True):
        if not workspace.contains(v.spawn.position_m):
            raise vnode.get("spawn").get("position").error(
                f"a position inside the workspace {list(workspace.min_m)}..{list(workspace.max_m)}"
            )

    obstacle_nodes = node.get("obstacles", []).list()
    obstacles = tuple(_parse_obstacle(o, base_dir, vehicle_index) for o in obstacle_nodes)
    _unique([o.name for o in obstacles], obstacle_nodes)
    for o, onode in zip(obstacles, obstacle_nodes, strict=True):
        path = o.randomize.along_path if o.randomize else None
        if path is not None and vehicles[path.vehicle].goal is None:
            raise onode.get("randomize").get("along_path").get("vehicle").error(
                "a vehicle that has a goal (the path runs from its spawn to its goal)"
            )
    world = World(name=name, source=node.source, description=description, home=home,
                  physics=physics, workspace=workspace, ground=ground, vehicles=vehicles,
                  goals=goals, obstacles=obstacles, task=task, train=train)
    check_world_sense(world, node)
    return world


def _parse_encounter_world(node: Node, base_dir: Path, task: Node | None, train: Node | None,
                           **fields) -> World:
    """A world whose vehicles and goals an `encounter:` section draws every episode: drone0..N-1
    with goals goal0..N-1, their written spawns and goals those of the episode drawn from seed 0."""
    for key in ("vehicles", "goals"):
        if node.has(key):
            raise node.get(key).error(f"no {key}: beside encounter: (the encounter places every drone and goal)")
    workspace: Workspace = fields["workspace"]
    encounter = parse_encounter(node.get("encounter"), workspace, _parse_lidar)
    names = [f"drone{i}" for i in range(encounter.drones)]
    obstacle_nodes = node.get("obstacles", []).list()
    obstacles = tuple(_parse_obstacle(o, base_dir, {n: i for i, n in enumerate(names)}) for o in obstacle_nodes)
    _unique([o.name for o in obstacles], obstacle_nodes)
    if any(o.randomize is not None and o.randomize.along_path is not None for o in obstacles):
        k = next(i for i, o in enumerate(obstacles) if o.randomize and o.randomize.along_path)
        raise obstacle_nodes[k].get("randomize").get("along_path").error(
            "no along_path beside encounter: (the paths are drawn per episode)")
    first = draw_encounter(encounter, workspace, obstacles, np.random.default_rng(0), source=node.source)
    goals = tuple(GoalRegion(f"goal{i}", center, encounter.goal_size_m) for i, center in enumerate(first.goal_centers_m))
    vehicles = tuple(VehicleSpec(names[i], "iris", Spawn(first.spawns_m[i], first.yaws_rad[i]), i, encounter.lidar)
                     for i in range(encounter.drones))
    world = World(source=node.source, vehicles=vehicles, goals=goals, obstacles=obstacles,
                  encounter=encounter, task=task, train=train, **fields)
    check_world_sense(world, node)
    return world


def _unique(names: list[str], nodes: list[Node]) -> None:
    seen: set[str] = set()
    for name, node in zip(names, nodes, strict=True):
        if name in seen:
            raise node.get("name").error("a name not used before in this list")
        seen.add(name)


def _parse_home(node: Node) -> GeoHome:
    node.mapping()
    node.reject_unknown({"lat", "lon", "alt", "magnetic_year"})
    default = GeoHome()
    return GeoHome(
        lat_deg=_num(node.get("lat", default.lat_deg), minimum=-89.0, maximum=89.0),
        lon_deg=_num(node.get("lon", default.lon_deg), minimum=-180.0, maximum=180.0),
        alt_m=_num(node.get("alt", default.alt_m), minimum=-500.0, maximum=9000.0),
        magnetic_year=_num(node.get("magnetic_year", default.magnetic_year), minimum=2025.0, maximum=2029.99),  # WMM2025
    )


def _parse_physics(node: Node) -> PhysicsSettings:
    node.mapping()
    node.reject_unknown({"step_us", "gravity", "solver_iterations", "hard_ground_speed", "crash_tilt"})
    d = PhysicsSettings()
    return PhysicsSettings(
        step_us=node.get("step_us", d.step_us).integer(minimum=100, maximum=100_000),
        gravity_m_s2=_num(node.get("gravity", d.gravity_m_s2), non_negative=True, maximum=100.0),
        solver_iterations=node.get("solver_iterations", d.solver_iterations).integer(minimum=1, maximum=500),
        hard_ground_speed_m_s=_num(node.get("hard_ground_speed", d.hard_ground_speed_m_s), positive=True,
                                     maximum=MAX_SPEED_M_S),
        crash_tilt_deg=_num(node.get("crash_tilt", d.crash_tilt_deg), positive=True, maximum=180.0),
    )


def _parse_box(node: Node, what: str, *, strict: bool = True) -> Workspace:
    node.mapping()
    if strict:
        node.reject_unknown({"min", "max"})
    lo = _vec(node.get("min"), 3)
    hi_node = node.get("max")
    hi = _vec(hi_node, 3)
    if not all(high > low for low, high in zip(lo, hi, strict=True)):
        raise hi_node.error(f"3 numbers each greater than {what}.min {list(lo)}")
    return Workspace(lo, hi)


def _parse_goal(node: Node) -> GoalRegion:
    node.mapping()
    node.reject_unknown({"name", "center", "size", "randomize"})
    name = node.get("name").string(max_chars=NAME_MAX_CHARS)
    center = _vec(node.get("center"), 3)
    size = _vec(node.get("size"), 3, positive=True)
    rmin = rmax = None
    if node.has("randomize"):
        box = _parse_box(node.get("randomize"), "randomize")
        rmin, rmax = box.min_m, box.max_m
    return GoalRegion(name, center, size, rmin, rmax)


def _parse_spawn(node: Node) -> Spawn:
    node.mapping()
    node.reject_unknown({"position", "yaw", "randomize"})
    position = _vec(node.get("position"), 3)
    yaw = math.radians(_num(node.get("yaw", 0.0), minimum=-360.0, maximum=360.0))
    rpos, ryaw = (0.0, 0.0, 0.0), 0.0
    if node.has("randomize"):
        r = node.get("randomize")
        r.mapping()
        r.reject_unknown({"position", "yaw"})
        rpos = _vec(r.get("position", [0.0, 0.0, 0.0]), 3, non_negative=True)
        ryaw = math.radians(_num(r.get("yaw", 0.0), non_negative=True, maximum=180.0))
    return Spawn(position, yaw, rpos, ryaw)


def _parse_lidar(node: Node) -> LidarConfig:
    node.mapping()
    node.reject_unknown({"horizontal", "up", "down", "range", "near", "crash", "filter_window", "flags"})
    d = LidarConfig()
    groups: dict[str, tuple[int, float]] = {}
    for group, (rays, fov) in {"horizontal": (d.horizontal_rays, d.horizontal_fov_deg),
                               "up": (d.up_rays, d.up_fov_deg), "down": (d.down_rays, d.down_fov_deg)}.items():
        g = node.get(group, {})
        g.mapping()
        g.reject_unknown({"rays", "fov"})
        max_fov = 360.0 if group == "horizontal" else 180.0
        groups[group] = (g.get("rays", rays).integer(minimum=0, maximum=1000),
                         _num(g.get("fov", fov), non_negative=True, maximum=max_fov))
    range_m = _num(node.get("range", d.range_m), positive=True, maximum=1000.0)
    near = _num(node.get("near", d.near_m), non_negative=True, maximum=range_m)
    crash_node = node.get("crash", d.crash_m)
    crash = _num(crash_node, non_negative=True)
    if crash > near:
        raise crash_node.error(f"a distance not above near ({near:g})")
    flags_node = node.get("flags", list(d.flag_groups))
    flags = tuple(f.string(LIDAR_GROUPS) for f in flags_node.list())
    return LidarConfig(
        horizontal_rays=groups["horizontal"][0], horizontal_fov_deg=groups["horizontal"][1],
        up_rays=groups["up"][0], up_fov_deg=groups["up"][1],
        down_rays=groups["down"][0], down_fov_deg=groups["down"][1],
        range_m=range_m, near_m=near, crash_m=crash,
        filter_window=node.get("filter_window", d.filter_window).integer(minimum=1, maximum=100),
        flag_groups=flags,
    )


def _parse_vehicle(node: Node, goal_index: dict[str, int]) -> VehicleSpec:
    node.mapping()
    node.reject_unknown({"name", "model", "spawn", "goal", "lidar"})
    name = node.get("name").string(max_chars=NAME_MAX_CHARS)
    model = node.get("model", "iris").string(VEHICLE_MODELS)
    spawn = _parse_spawn(node.get("spawn"))
    goal = None
    if node.has("goal"):
        goal_node = node.get("goal")
        goal_name = goal_node.string(max_chars=NAME_MAX_CHARS)
        if goal_name not in goal_index:
            raise goal_node.error(f"the name of a goal in world.goals ({', '.join(goal_index) or 'none defined'})")
        goal = goal_index[goal_name]
    lidar = _parse_lidar(node.get("lidar", {}))
    return VehicleSpec(name, model, spawn, goal, lidar)


def _parse_shape(node: Node, base_dir: Path, kind_key: str = "shape") -> Shape:
    """Shape fields of an obstacle or variant node (keys: shape, size, radius, height, opening, file, scale)."""
    kind = node.get(kind_key).string(SHAPE_KINDS)
    given = set(node.mapping()) & (SHAPE_KEYS - {"shape", kind_key})
    for key in sorted(given - set(SHAPE_KEYS_OF[kind])):
        child = node.get(key)
        raise ConfigError(f"{child.source}: {child.path}: a {kind} has no `{key}` (it would be ignored); "
                          f"a {kind} takes {', '.join(SHAPE_KEYS_OF[kind])}")
    if kind in ("box", "wall"):
        size = _vec(node.get("size"), 3, positive=True)
        opening = _parse_opening(node.get("opening"), size) if kind == "wall" and node.has("opening") else None
        return Shape(kind, size_m=size, opening=opening)
    if kind == "cylinder":
        return Shape(kind, radius_m=_num(node.get("radius"), positive=True),
                     height_m=_num(node.get("height"), positive=True))
    if kind == "sphere":
        return Shape(kind, radius_m=_num(node.get("radius"), positive=True))
    file_node = node.get("file")
    mesh_path = (base_dir / file_node.string()).resolve()
    if not mesh_path.is_file():
        raise file_node.error("a mesh file (.obj) relative to the world file")
    scale = _vec(node.get("scale", [1.0, 1.0, 1.0]), 3, positive=True)
    size = _vec(node.get("size"), 3, positive=True)  # bounding box, for placement on the ground
    return Shape(kind, size_m=size, mesh_file=str(mesh_path), mesh_scale=scale)


def _parse_opening(node: Node, wall_size: tuple[float, ...]) -> Opening:
    node.mapping()
    node.reject_unknown({"offset", "bottom", "width", "height"})
    o = Opening(
        offset_m=_num(node.get("offset", 0.0)),
        bottom_m=_num(node.get("bottom"), non_negative=True),
        width_m=_num(node.get("width"), positive=True),
        height_m=_num(node.get("height"), positive=True),
    )
    length, _, height = wall_size
    if abs(o.offset_m) + o.width_m / 2.0 > length / 2.0 or o.bottom_m + o.height_m > height:
        raise node.error(f"an opening inside the wall (length {length:g}, height {height:g})")
    return o


SHAPE_KEYS = {"shape", "size", "radius", "height", "opening", "file", "scale"}
SHAPE_KEYS_OF = {"box": ("size",), "wall": ("size", "opening"), "cylinder": ("radius", "height"),
                 "sphere": ("radius",), "mesh": ("file", "scale", "size")}
"""The shape keys each kind reads; any other shape key given to it is an error, not ignored."""


def _parse_obstacle(node: Node, base_dir: Path, vehicle_index: dict[str, int]) -> Obstacle:
    node.mapping()
    node.reject_unknown(SHAPE_KEYS | {"name", "position", "yaw", "color", "mover", "mass", "randomize"})
    name = node.get("name").string(max_chars=NAME_MAX_CHARS)
    shape = _parse_shape(node, base_dir)
    position = _vec(node.get("position"), 3)
    yaw = math.radians(_num(node.get("yaw", 0.0), minimum=-360.0, maximum=360.0))
    color = _vec(node.get("color", [0.6, 0.6, 0.6, 1.0]), 4, non_negative=True, maximum=1.0)
    mover = _parse_mover(node.get("mover")) if node.has("mover") else None
    mass = _num(node.get("mass", 1.0), positive=True, maximum=1e6)
    randomize = None
    if node.has("randomize"):
        if mover is not None:
            raise node.get("randomize").error("no randomize on a moving obstacle (its mover is seeded)")
        randomize = _parse_obstacle_randomization(node.get("randomize"), base_dir, vehicle_index)
    if shape.kind == "wall" and mover is not None:
        raise node.get("mover").error("no mover on a wall")
    return Obstacle(name, shape, position, yaw, color, mover, mass, randomize)  # type: ignore[arg-type]


def _parse_mover(node: Node) -> PatrolMover | RandomLegsMover:
    node.mapping()
    kind = node.get("type").string(("patrol", "random_legs"))
    speed = _num(node.get("speed"), positive=True, maximum=MAX_SPEED_M_S)
    if kind == "patrol":
        node.reject_unknown({"type", "speed", "points", "random_start"})
        points = tuple(_vec(p, 3) for p in node.get("points").list(min_len=2))
        return PatrolMover(points, speed, node.get("random_start", False).boolean())
    node.reject_unknown({"type", "speed", "min", "max"})
    box = _parse_box(node, "mover", strict=False)
    return RandomLegsMover(box.min_m, box.max_m, speed)


def _parse_obstacle_randomization(node: Node, base_dir: Path, vehicle_index: dict[str, int]) -> ObstacleRandomization:
    node.mapping()
    node.reject_unknown({"along_path", "position", "yaw", "variants"})
    along = None
    if node.has("along_path"):
        a = node.get("along_path")
        a.mapping()
        a.reject_unknown({"vehicle", "fraction", "lateral"})
        vnode = a.get("vehicle")
        vname = vnode.string(max_chars=NAME_MAX_CHARS)
        if vname not in vehicle_index:
            raise vnode.error(f"the name of a vehicle ({', '.join(vehicle_index)})")
        fnode = a.get("fraction")
        lo, hi = _vec(fnode, 2, non_negative=True)
        if not lo <= hi <= 1.0:
            raise fnode.error("[low, high] with 0 <= low <= high <= 1")
        along = AlongPath(vehicle_index[vname], (lo, hi), _num(a.get("lateral", 0.0), non_negative=True))
    position = _vec(node.get("position", [0.0, 0.0, 0.0]), 3, non_negative=True)
    yaw = math.radians(_num(node.get("yaw", 0.0), non_negative=True, maximum=180.0))
    variants = []
    for v in node.get("variants", []).list():
        v.mapping()
        v.reject_unknown(SHAPE_KEYS)
        variants.append(_parse_shape(v, base_dir))
    return ObstacleRandomization(along, position, yaw, tuple(variants))


MAX_EXTENT_M = 10_000.0
"""Every length, position and size of a world lies within +-10 km (a bound on absurd values
that would otherwise overflow float32 later)."""
MAX_SPEED_M_S = 100.0


def _vec(node: Node, length: int = 3, *, maximum: float = MAX_EXTENT_M, **kwargs: bool) -> tuple[float, ...]:
    """`Node.vector`, also refusing inf and values beyond +-`maximum`."""
    values = node.vector(length, **kwargs)
    if not all(math.isfinite(v) and abs(v) <= maximum for v in values):
        raise node.error(f"{length} finite numbers within +-{maximum:g}")
    return values


def _num(node: Node, *, maximum: float | None = None, minimum: float | None = None,
         **kwargs: float | bool | None) -> float:
    """`Node.number`, also refusing inf; bounded to +-MAX_EXTENT_M unless given bounds."""
    value = node.number(minimum=-MAX_EXTENT_M if minimum is None else minimum,  # type: ignore[arg-type]
                        maximum=MAX_EXTENT_M if maximum is None else maximum, **kwargs)
    if not math.isfinite(value):
        raise node.error("a finite number")
    return value
