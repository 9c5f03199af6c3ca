"""Observation features: each a small class with a size, fixed bounds and a function of `DroneView`.

The scenario file lists features by name; the observation is their concatenation in that order.
Each list item is a name (`- velocity`) or a one-key mapping with options
(`- position: {decimals: 0}`, `- lidar: [horizontal, up, down]`, `- dummy: 11`).

| name | size | value (world ENU, metres, m/s, radians) | bounds |
|---|---|---|---|
| `position` | 3 | x, y, z; `decimals: N` rounds (thesis: "rounded x,y,z") | workspace |
| `orientation` | 3 | roll, pitch, yaw; `decimals: N` rounds | [-pi, pi] |
| `velocity` | 3 | vx, vy, vz | +- max speed (5 m/s) |
| `goal_position` | 3 | the drone's goal point | workspace |
| `goal_offset` | 3 | goal minus position | +- workspace diagonal |
| `own_id` | 1 | drone index | [0, max(1, drones-1)] |
| `own_priority` | 1 | the drone's priority (see below) | [0, 1] |
| `other_priority` | count | the other drones' priorities | [0, 1] |
| `transponder` | 6*count | other drones' x, y, z, vx, vy, vz (zeros if absent) | workspace, +- max speed |
| `travel_goal_offset` | 3 | goal minus position in the own travel frame (right, forward, up) | +- workspace diagonal |
| `travel_velocity` | 3 | own velocity in the own travel frame | +- max speed |
| `travel_others` | 6*count | per other drone: its position minus own, its velocity minus own, in the own travel frame (zeros if absent; see below for `order` and `absent`) | +- diagonal, +- 2 max speed |
| `line_distance` | 1 | distance from the line through start and goal | [0, diagonal] |
| `lidar` | rays | ray distances of the listed groups (default all three) | [0, range] |
| `lidar_change` | rays | each ray's distance minus its distance one action earlier (0 at reset): how the surroundings moved relative to the drone | +- range |
| `lidar_flags` | 2 | the lidar's near and crash flags (0/1) | [0, 1] |
| `dummy` | N | zeros, to keep input sizes equal across scenarios | [-1, 1] |

`count` defaults to drones-1 (at least 1). One network for worlds of 2, 3 and 4 drones: give
`travel_others: {count: 3, order: nearest, absent: far}` in all of them (the encounter family
does): the observation has the same size everywhere, slot 0 is always the nearest other drone
(`order: nearest`: slots sorted by distance, nearest first; default `index`: by drone number),
and a slot with no drone behind it reads `ABSENT_FAR` (`absent: far`): as far behind as any
drone can be (forward = minus the workspace diagonal, right and up 0) and moving exactly like
the own drone (relative velocity 0), i.e. a drone that is never closing and never near, so a
rule or ORCA testing distances or closing speeds reads no conflict there (default `zeros`: all
six zero, which reads as a drone at the own position). Priority: the rank of the drone under the scenario's
`task.priority` rule (`envs/priority.py`; default `lower_coordinate_yields`: lower north, then
lower east start coordinate = lower priority, the thesis's "lower GPS coordinates hovers"),
scaled to [0, 1]; with one drone it is 1.

The travel frame of a drone (agent-relative features): forward = the horizontal direction from
its start to its goal (north when the goal is straight above), right = forward turned clockwise,
up = up; the same frame as `frame: goal` actions (0 right, 3 forward), so two drones on a
head-on course see mirror-image situations as the same numbers.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from sitl_bridge.envs.view import DroneView, ScenarioLimits
from sitl_bridge.errors import ConfigError, Node
from sitl_bridge.jit import kernel

LIDAR_GROUPS = ("horizontal", "up", "down")


@dataclass(frozen=True)
class Feature:
    """One named block of the observation vector."""

    name: str
    low: np.ndarray
    high: np.ndarray
    compute: Callable[[DroneView], np.ndarray]
    labels: tuple[str, ...] = ()
    """Each element in words, where that helps a reader (lidar: each ray's direction)."""
    groups: tuple[str, ...] = ()
    """Each element's group, where the feature has groups (lidar: horizontal, up, down)."""

    @property
    def size(self) -> int:
        return int(self.low.shape[0])

    def __call__(self, view: DroneView) -> np.ndarray:
        """The feature's values for `view`, finite and clipped to the bounds."""
        value = np.asarray(self.compute(view), dtype=np.float64).reshape(-1)
        value = np.nan_to_num(value, nan=0.0, posinf=0.0, neginf=0.0)
        return np.clip(value, self.low, self.high)


class ObservationAssembler:
    """One drone's observation vector from a list of features, built once per scenario: every
    feature's values concatenated, then made finite and clipped to the bounds in one pass over
    the whole vector, and cast to float32. The same numbers as concatenating each
    `Feature(view)` (each step is elementwise), without a NumPy call per feature and step."""

    def __init__(self, features: Sequence[Feature]) -> None:
        self.features = tuple(features)
        self._computes = tuple(f.compute for f in self.features)
        self.low = np.concatenate([f.low for f in self.features]).astype(np.float64)
        self.high = np.concatenate([f.high for f in self.features]).astype(np.float64)

    def __call__(self, view: DroneView) -> np.ndarray:
        value = np.concatenate([np.asarray(compute(view), dtype=np.float64).reshape(-1)
                                for compute in self._computes])
        return finite_clipped_float32(value, self.low, self.high)


@kernel()
def finite_clipped_float32(value: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """`Feature.__call__`'s last steps over a whole vector, then float32: NaN and +-inf become 0
    (`nan_to_num(nan=0, posinf=0, neginf=0)`), then each value is clipped to [low, high]
    (`np.clip`: below low -> low, above high -> high)."""
    out = np.empty(value.shape[0], dtype=np.float32)
    for k in range(value.shape[0]):
        x = value[k]
        if not np.isfinite(x):
            x = 0.0
        if x < low[k]:  # np.clip is minimum(maximum(x, low), high)
            x = low[k]
        if x > high[k]:
            x = high[k]
        out[k] = x
    return out


def _rounded(values: np.ndarray, decimals: int | None) -> np.ndarray:
    return values if decimals is None else np.round(values, decimals)


def _decimals(options: Node) -> int | None:
    if options.value is None:
        return None
    options.reject_unknown({"decimals"})
    node = options.get("decimals", None)
    return None if node.value is None else node.integer(minimum=0, maximum=6)


def _count(options: Node, limits: ScenarioLimits, extra: frozenset[str] = frozenset()) -> int:
    if options.value is None:
        return max(1, limits.num_drones - 1)
    options.reject_unknown({"count", *extra})
    return options.get("count", max(1, limits.num_drones - 1)).integer(minimum=1, maximum=64)


def _padded(rows: np.ndarray, count: int, width: int) -> np.ndarray:
    out = np.zeros((count, width))
    n = min(count, rows.shape[0])
    out[:n] = rows[:n]
    return out


def _position(options: Node, limits: ScenarioLimits) -> Feature:
    decimals = _decimals(options)
    return Feature("position", limits.workspace_low_enu_m.astype(float),
                   limits.workspace_high_enu_m.astype(float),
                   lambda v: _rounded(v.position_enu_m, decimals))


def _orientation(options: Node, limits: ScenarioLimits) -> Feature:
    decimals = _decimals(options)
    bound = np.full(3, math.pi)
    return Feature("orientation", -bound, bound, lambda v: _rounded(v.euler_enu_rad, decimals))


def _velocity(options: Node, limits: ScenarioLimits) -> Feature:
    _no_options(options)
    bound = np.full(3, limits.max_speed_m_s)
    return Feature("velocity", -bound, bound, lambda v: v.velocity_enu_m_s)


def _goal_position(options: Node, limits: ScenarioLimits) -> Feature:
    _no_options(options)
    return Feature("goal_position", limits.workspace_low_enu_m.astype(float),
                   limits.workspace_high_enu_m.astype(float), lambda v: v.goal_enu_m)


def _goal_offset(options: Node, limits: ScenarioLimits) -> Feature:
    _no_options(options)
    bound = np.full(3, limits.diagonal_m)
    return Feature("goal_offset", -bound, bound, lambda v: v.goal_enu_m - v.position_enu_m)


def _own_id(options: Node, limits: ScenarioLimits) -> Feature:
    _no_options(options)
    # high at least 1: a one-drone scenario keeps a proper range (and W matches TW for transfer)
    return Feature("own_id", np.zeros(1), np.full(1, float(max(1, limits.num_drones - 1))),
                   lambda v: np.array([float(v.index)]))


def _own_priority(options: Node, limits: ScenarioLimits) -> Feature:
    _no_options(options)
    return Feature("own_priority", np.zeros(1), np.ones(1), lambda v: np.array([v.priority]))


def _other_priority(options: Node, limits: ScenarioLimits) -> Feature:
    count = _count(options, limits)
    return Feature("other_priority", np.zeros(count), np.ones(count),
                   lambda v: _padded(v.other_priorities.reshape(-1, 1), count, 1).reshape(-1))


def _transponder(options: Node, limits: ScenarioLimits) -> Feature:
    count = _count(options, limits)
    speed = np.full(3, limits.max_speed_m_s)
    low = np.tile(np.concatenate([limits.workspace_low_enu_m, -speed]), count)
    high = np.tile(np.concatenate([limits.workspace_high_enu_m, speed]), count)

    def compute(v: DroneView) -> np.ndarray:
        rows = np.hstack([v.others_position_enu_m.reshape(-1, 3),
                          v.others_velocity_enu_m_s.reshape(-1, 3)])
        return _padded(rows, count, 6).reshape(-1)

    return Feature("transponder", low.astype(float), high.astype(float), compute)


def travel_frame(start_enu_m: np.ndarray, goal_enu_m: np.ndarray) -> np.ndarray:
    """Rows right, forward, up (ENU unit vectors) of the drone's travel frame; R @ v_enu."""
    dx, dy = float(goal_enu_m[0] - start_enu_m[0]), float(goal_enu_m[1] - start_enu_m[1])
    length = math.hypot(dx, dy)
    fx, fy = (0.0, 1.0) if length < 1e-6 else (dx / length, dy / length)
    return np.array([[fy, -fx, 0.0], [fx, fy, 0.0], [0.0, 0.0, 1.0]])


def _travel_goal_offset(options: Node, limits: ScenarioLimits) -> Feature:
    _no_options(options)
    bound = np.full(3, limits.diagonal_m)
    return Feature("travel_goal_offset", -bound, bound,
                   lambda v: travel_frame(v.start_enu_m, v.goal_enu_m) @ (v.goal_enu_m - v.position_enu_m))


def _travel_velocity(options: Node, limits: ScenarioLimits) -> Feature:
    _no_options(options)
    bound = np.full(3, limits.max_speed_m_s)
    return Feature("travel_velocity", -bound, bound,
                   lambda v: travel_frame(v.start_enu_m, v.goal_enu_m) @ v.velocity_enu_m_s)


TRAVEL_OTHERS_ORDERS = ("index", "nearest")
TRAVEL_OTHERS_ABSENT = ("zeros", "far")


def absent_far(diagonal_m: float) -> np.ndarray:
    """`travel_others`' six values for an empty slot under `absent: far`: a drone the workspace
    diagonal straight behind (the farthest any drone can be), with no relative velocity."""
    return np.array([0.0, -diagonal_m, 0.0, 0.0, 0.0, 0.0])


def _choice(options: Node, key: str, choices: tuple[str, ...]) -> str:
    if options.value is None or not options.has(key):
        return choices[0]
    return options.get(key).string(choices)


def _travel_others(options: Node, limits: ScenarioLimits) -> Feature:
    count = _count(options, limits, frozenset({"order", "absent"}))
    nearest = _choice(options, "order", TRAVEL_OTHERS_ORDERS) == "nearest"
    far = _choice(options, "absent", TRAVEL_OTHERS_ABSENT) == "far"
    bound = np.tile(np.concatenate([np.full(3, limits.diagonal_m), np.full(3, 2 * limits.max_speed_m_s)]),
                    count)
    empty = absent_far(limits.diagonal_m) if far else np.zeros(6)

    def compute(v: DroneView) -> np.ndarray:
        rotation = travel_frame(v.start_enu_m, v.goal_enu_m)
        offsets = (v.others_position_enu_m.reshape(-1, 3) - v.position_enu_m) @ rotation.T
        closing = (v.others_velocity_enu_m_s.reshape(-1, 3) - v.velocity_enu_m_s) @ rotation.T
        rows = np.hstack([offsets, closing])
        if nearest:  # stable: equal distances keep drone order
            rows = rows[np.argsort(np.linalg.norm(offsets, axis=1), kind="stable")]
        out = np.tile(empty, (count, 1))
        n = min(count, rows.shape[0])
        out[:n] = rows[:n]
        return out.reshape(-1)

    return Feature("travel_others", -bound, bound, compute)


def distance_from_line(point: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Distance of `point` from the infinite line through `a` and `b` (from `a` if they coincide)."""
    direction = b - a
    length = float(np.linalg.norm(direction))
    if length < 1e-9:
        return float(np.linalg.norm(point - a))
    return float(np.linalg.norm(np.cross(point - a, direction / length)))


def _line_distance(options: Node, limits: ScenarioLimits) -> Feature:
    _no_options(options)
    return Feature("line_distance", np.zeros(1), np.full(1, limits.diagonal_m),
                   lambda v: np.array([distance_from_line(v.position_enu_m, v.start_enu_m,
                                                          v.goal_enu_m)]))


def _lidar_groups(options: Node) -> list[str]:
    """The ray groups a lidar feature lists (`[horizontal, up]` or `{groups: [...]}`; default all)."""
    if options.value is None:
        return list(LIDAR_GROUPS)
    if isinstance(options.value, list):
        return [item.string(LIDAR_GROUPS) for item in options.list(min_len=1)]
    options.reject_unknown({"groups"})
    return [item.string(LIDAR_GROUPS) for item in options.get("groups").list(min_len=1)]


def _lidar(options: Node, limits: ScenarioLimits) -> Feature:
    groups = _lidar_groups(options)
    size = sum(limits.lidar_rays[g] for g in groups)
    return Feature("lidar", np.zeros(size), np.full(size, limits.lidar_range_m),
                   lambda v: np.concatenate([v.lidar[g] for g in groups]),
                   tuple(label for g in groups for label in limits.lidar_labels.get(g, ())),
                   tuple(g for g in groups for _ in range(limits.lidar_rays[g])))


def _lidar_change(options: Node, limits: ScenarioLimits) -> Feature:
    # One lidar scan cannot tell a walker coming toward the drone's path from one walking away
    # (the street's crashes happen there); the change over the last action shows the motion.
    groups = _lidar_groups(options)
    size = sum(limits.lidar_rays[g] for g in groups)

    def compute(v: DroneView) -> np.ndarray:
        if v.previous_lidar is None:
            return np.zeros(size)
        return np.concatenate([v.lidar[g] - v.previous_lidar[g] for g in groups])

    bound = np.full(size, limits.lidar_range_m)
    return Feature("lidar_change", -bound, bound, compute)


def _lidar_flags(options: Node, limits: ScenarioLimits) -> Feature:
    _no_options(options)
    return Feature("lidar_flags", np.zeros(2), np.ones(2),
                   lambda v: np.array([float(v.near_obstacle), float(v.crashed)]))


def _dummy(options: Node, limits: ScenarioLimits) -> Feature:
    if isinstance(options.value, dict):
        options.reject_unknown({"size"})
        size = options.get("size").integer(minimum=1, maximum=10_000)
    else:
        size = options.integer(minimum=1, maximum=10_000)
    # Always 0; declared in [-1, 1] because a Box dimension with low == high is degenerate.
    return Feature("dummy", -np.ones(size), np.ones(size), lambda v: np.zeros(size))


def _no_options(options: Node) -> None:
    if options.value is not None and options.value != {}:
        raise options.error("no options")


FEATURES: dict[str, Callable[[Node, ScenarioLimits], Feature]] = {
    "position": _position,
    "orientation": _orientation,
    "velocity": _velocity,
    "goal_position": _goal_position,
    "goal_offset": _goal_offset,
    "own_id": _own_id,
    "own_priority": _own_priority,
    "other_priority": _other_priority,
    "transponder": _transponder,
    "travel_goal_offset": _travel_goal_offset,
    "travel_velocity": _travel_velocity,
    "travel_others": _travel_others,
    "line_distance": _line_distance,
    "lidar": _lidar,
    "lidar_change": _lidar_change,
    "lidar_flags": _lidar_flags,
    "dummy": _dummy,
}


FEATURE_MEANINGS: dict[str, tuple[str, str]] = {
    "position": ("x, y, z (world ENU)", "m"),
    "orientation": ("roll, pitch, yaw (world ENU)", "rad"),
    "velocity": ("vx, vy, vz (world ENU)", "m/s"),
    "goal_position": ("the drone's goal point x, y, z", "m"),
    "goal_offset": ("goal minus position", "m"),
    "own_id": ("drone index", "-"),
    "own_priority": ("own priority rank under task.priority, scaled (1 = right of way)", "-"),
    "other_priority": ("the other drones' priority ranks", "-"),
    "transponder": ("per other drone: x, y, z, vx, vy, vz", "m, m/s"),
    "travel_goal_offset": ("goal minus position: right, forward, up of the own travel direction", "m"),
    "travel_velocity": ("own velocity: right, forward, up of the own travel direction", "m/s"),
    "travel_others": ("per other drone: relative x, y, z and relative vx, vy, vz (right, forward, "
                      "up of the own travel direction)", "m, m/s"),
    "line_distance": ("distance from the start-goal line", "m"),
    "lidar": ("ray distances (range when nothing is hit)", "m"),
    "lidar_change": ("each ray's distance minus its distance one action earlier", "m"),
    "lidar_flags": ("near, crash flags of the lidar", "0/1"),
    "dummy": ("zeros (input padding for transfer)", "-"),
}
"""What each feature's values are and their unit (the scenario manual's table)."""


def parse_observation(node: Node, limits: ScenarioLimits) -> list[Feature]:
    """Parse the `observation:` list into features, in order."""
    features = []
    for item in node.list(min_len=1):
        if isinstance(item.value, str):
            name, options = item.value, Node(None, item.source, item.path)
        elif isinstance(item.value, dict) and len(item.value) == 1:
            name, options = next(iter(item.items()))
        else:
            raise item.error("a feature name or a one-key mapping {name: options}")
        if name not in FEATURES:
            raise ConfigError(f"{item.source}: {item.path}: unknown observation feature "
                              f"{name!r} (expected one of {', '.join(FEATURES)})")
        features.append(FEATURES[name](options, limits))
    return features


def observation_layout(observation: Sequence[Feature]) -> dict[str, slice]:
    """Feature name -> its slice of one drone's observation vector (`task.observation`), in order.
    A name listed twice keeps its first block under `name` and the later ones as `name@2`, ..."""
    layout: dict[str, slice] = {}
    start = 0
    for feature in observation:
        key, n = feature.name, 1
        while key in layout:
            n += 1
            key = f"{feature.name}@{n}"
        layout[key] = slice(start, start + feature.size)
        start += feature.size
    return layout


def index_words(observation: Sequence[Feature]) -> dict[int, str]:
    """Observation index (of `task.observation`) -> what it points at in words, for the features that say it (each lidar
    ray's direction: `ahead`, `below, 37 deg ahead`); others are left out."""
    words: dict[int, str] = {}
    start = 0
    for feature in observation:
        words.update({start + i: label for i, label in enumerate(feature.labels)})
        start += feature.size
    return words
