"""Path distance: the length of the shortest obstacle-free path from a point to a goal region.

`closer_to_goal: {along: path}` (envs/rewards.py) pays metres gained along this path instead of
along the straight line, so shaping leads around obstacles rather than into them. It works for
any static layout a scenario file can write:

* Grid: nodes every `cell_m` over the world's workspace box, from its `min` corner (a workspace
  side that is not a multiple of `cell_m` ends at the last whole cell).
* Occupancy: a node is blocked when it lies within `clearance_m` of a static obstacle. Each
  static obstacle (every shape: box, wall with its opening, cylinder, sphere, mesh; with yaw) is
  built by `physics.bodies.create_obstacle`, the one place that turns a shape into collision
  geometry, on a private pybullet DIRECT client, and the nodes inside its grown bounding box are
  probed with a sphere of radius `clearance_m` (`getClosestPoints`). Moving obstacles (movers)
  are ignored; the ground is no obstacle (the workspace bounds the path from below).
* Search: Lazy Theta* (Nash, Koenig and Tovey 2010) run to exhaustion from the goal box, in a
  compiled kernel (`sitl_bridge.jit`): Dijkstra over the 26-connected grid (moves weighted by
  their Euclidean length; a diagonal only where unit axis steps over free nodes could make it,
  so it never slips between two blocked nodes), in which every node keeps the farthest parent it
  sees (the goal box itself when in sight) and its length is the parent's plus the straight
  segment. Lengths so follow straight lines at any angle (plain 26-connected Dijkstra is up to
  8 % long between the grid's directions). A segment is in sight when every point sampled along
  it (each quarter cell) is nearer to a free node than to a blocked one. Free nodes within a
  cell of the goal box start the search with their straight distance to it (0 inside).
* Query `PathField.distance(p)`: the least over the reachable corners k of p's cell of
  field[k] + |p - k| and, for their parents q in p's sight, field[q] + |p - q| (the goal box
  as parent: p's straight distance to it; 0 inside the box). So it is exact in free space and
  continuous but for a few centimetres where a cell beside an obstacle changes. A point with no
  reachable corner (inside a grown obstacle, outside the workspace) gets its nearest reachable
  node's value plus the distance to that node.
* Cache: `path_field` keeps the occupancy per (workspace, grid, static obstacle poses) and the
  field per (occupancy, goal box), so scenarios whose obstacles or goal are drawn per episode
  compute again only when the layout changed (`worlds/random_goal.yaml`: the search only).
  CPU time for two_blocks' 12 x 15 x 6 m at 0.5 m (10075 nodes): about 10 ms occupancy and
  15 ms search; a query about 10 us.
"""

from __future__ import annotations

import heapq
import itertools
import math
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from sitl_bridge.jit import kernel
from sitl_bridge.physics.bodies import create_obstacle
from sitl_bridge.physics.bullet import p
from sitl_bridge.world import GoalPlacement, ObstaclePlacement, Workspace

CELL_M = 0.5
"""Default grid spacing (m)."""
CLEARANCE_M = 0.4
"""Default clearance kept from static obstacles (m): the lidar's default crash distance."""
MAX_NODES = 4_000_000
"""Largest grid accepted (about 100 MB of field and occupancy): a finer `cell_m` is refused."""
CACHE_SIZE = 16
"""Occupancies and fields kept per process (least recently used dropped first)."""


@dataclass(frozen=True)
class PathGrid:
    """How the path distance is computed: grid spacing and clearance from obstacles (m)."""

    cell_m: float = CELL_M
    clearance_m: float = CLEARANCE_M



def _moves() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The 26 moves: (26, 3) offsets, their lengths in cells, and for each the ways to make it
    by unit axis steps inside its cube: (26, 6, 2, 3) offsets of the nodes passed on the way
    (padded by repeating), and how many ways each move has (1, 2 or 6)."""
    offsets = [m for m in itertools.product((-1, 0, 1), repeat=3) if m != (0, 0, 0)]
    routes = np.zeros((len(offsets), 6, 2, 3), dtype=np.int64)
    counts = np.zeros(len(offsets), dtype=np.int64)
    for m, offset in enumerate(offsets):
        axes = [a for a in range(3) if offset[a]]
        orders = list(itertools.permutations(axes)) if len(axes) > 1 else [tuple(axes)]
        counts[m] = len(orders)
        for r, order in enumerate(orders):
            node = np.zeros(3, dtype=np.int64)
            passed = []
            for axis in order[:-1]:
                node[axis] += offset[axis]
                passed.append(node.copy())
            passed = passed or [np.array(offset)]
            routes[m, r] = [passed[0], passed[-1]]
    offsets_array = np.array(offsets, dtype=np.int64)
    return offsets_array, np.linalg.norm(offsets_array, axis=1), routes, counts


_OFFSETS, _LENGTHS, _ROUTES, _ROUTE_COUNTS = _moves()


@kernel()
def _nearest(q: float, nodes: int) -> tuple[int, int]:
    """The nodes (first and last, clipped to 0 .. nodes - 1) nearest to a grid coordinate: two
    when it lies halfway between them, else one."""
    low = math.floor(q)
    frac = q - low
    first = low if frac <= 0.5 + 1e-9 else low + 1
    last = low + 1 if frac >= 0.5 - 1e-9 else first
    return max(min(first, nodes - 1), 0), max(min(last, nodes - 1), 0)


@kernel(_nearest)
def _point_clear(free: np.ndarray, shape: np.ndarray, qx: float, qy: float, qz: float) -> bool:
    """Whether the node nearest to a point (in grid units) is free (on a tie: any of them)."""
    ny, nz = shape[1], shape[2]
    x0, x1 = _nearest(qx, shape[0])
    y0, y1 = _nearest(qy, ny)
    z0, z1 = _nearest(qz, nz)
    for ix in range(x0, x1 + 1):
        for iy in range(y0, y1 + 1):
            for iz in range(z0, z1 + 1):
                if free[(ix * ny + iy) * nz + iz]:
                    return True
    return False


@kernel(_point_clear)
def _sight(free: np.ndarray, shape: np.ndarray, ax: float, ay: float, az: float, bx: float, by: float,
           bz: float) -> bool:
    """Whether the straight segment from a to b (grid units) stays closer to free nodes than to
    blocked ones (sampled every quarter cell along its longest axis)."""
    dx, dy, dz = bx - ax, by - ay, bz - az
    samples = int(math.ceil(4.0 * max(abs(dx), abs(dy), abs(dz))))
    for k in range(1, samples):
        t = k / samples
        if not _point_clear(free, shape, ax + t * dx, ay + t * dy, az + t * dz):
            return False
    return True


@kernel()
def _move_clear(free: np.ndarray, shape: np.ndarray, s: int, m: int, offsets: np.ndarray, routes: np.ndarray,
                route_counts: np.ndarray) -> bool:
    """Whether move m from node s can be made by unit axis steps over free nodes (so a diagonal
    never slips between two blocked nodes)."""
    ny, nz = shape[1], shape[2]
    sx, sy, sz = s // (ny * nz), (s // nz) % ny, s % nz
    for r in range(route_counts[m]):
        clear = True
        for k in range(2):
            node = ((sx + routes[m, r, k, 0]) * ny + sy + routes[m, r, k, 1]) * nz + sz + routes[m, r, k, 2]
            if not free[node]:
                clear = False
        if clear:
            return True
    return False


GOAL_PARENT = -2
"""Parent of a node that sees the goal box itself (its length: the straight distance to the box)."""


@kernel()
def _to_box(low: np.ndarray, high: np.ndarray, x: float, y: float, z: float) -> tuple[float, float, float]:
    """The point of the box [low, high] nearest to (x, y, z)."""
    return (min(max(x, low[0]), high[0]), min(max(y, low[1]), high[1]), min(max(z, low[2]), high[2]))


@kernel(_sight, _move_clear, _to_box)
def _path_lengths(free: np.ndarray, shape: np.ndarray, goal_low: np.ndarray, goal_high: np.ndarray,
                  offsets: np.ndarray, lengths: np.ndarray, routes: np.ndarray, route_counts: np.ndarray,
                  cell_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Path lengths (m) to the goal box [goal_low, goal_high] (grid units) over the free nodes of
    a flat (x, y, z) grid: Lazy Theta* (Nash, Koenig and Tovey 2010) run to exhaustion, i.e.
    Dijkstra over the 26 moves in which every node keeps the farthest parent it sees (the goal box
    itself when in sight), so lengths follow straight segments at any angle, not grid moves.
    Free nodes within a cell of the box start it, with their straight distance to the box.
    Returns the lengths and each node's parent (`GOAL_PARENT`: the box; -1: unreachable)."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    n = nx * ny * nz
    dist = np.full(n, np.inf)
    parent = np.full(n, -1, dtype=np.int64)
    done = np.zeros(n, dtype=np.bool_)
    heap = [(0.0, np.int64(0))]
    heap.pop()
    for i in range(n):
        x, y, z = i // (ny * nz), (i // nz) % ny, i % nz
        bx, by, bz = _to_box(goal_low, goal_high, float(x), float(y), float(z))
        gap = math.sqrt((bx - x) ** 2 + (by - y) ** 2 + (bz - z) ** 2)
        if free[i] and gap <= 1.0 + 1e-9:
            dist[i] = gap * cell_m
            parent[i] = GOAL_PARENT
            heapq.heappush(heap, (dist[i], np.int64(i)))
    while len(heap) > 0:
        d, s = heapq.heappop(heap)
        if done[s] or d > dist[s]:
            continue
        sx, sy, sz = s // (ny * nz), (s // nz) % ny, s % nz
        p_ = parent[s]
        if p_ == GOAL_PARENT:
            tx, ty, tz = _to_box(goal_low, goal_high, float(sx), float(sy), float(sz))
            seen = dist[s] <= cell_m + 1e-9 or _sight(free, shape, tx, ty, tz, sx, sy, sz)
        else:
            seen = _sight(free, shape, p_ // (ny * nz), (p_ // nz) % ny, p_ % nz, sx, sy, sz)
        if not seen:
            # the parent is out of sight: the best expanded neighbour instead (a grid move)
            best = np.inf
            for m in range(offsets.shape[0]):
                jx, jy, jz = sx + offsets[m, 0], sy + offsets[m, 1], sz + offsets[m, 2]
                if jx < 0 or jx >= nx or jy < 0 or jy >= ny or jz < 0 or jz >= nz:
                    continue
                j = (jx * ny + jy) * nz + jz
                if done[j] and dist[j] + lengths[m] * cell_m < best and _move_clear(free, shape, s, m, offsets,
                                                                                     routes, route_counts):
                    best = dist[j] + lengths[m] * cell_m
                    parent[s] = j
            dist[s] = best
        done[s] = True
        p_ = parent[s]
        px, py, pz = p_ // (ny * nz), (p_ // nz) % ny, p_ % nz
        for m in range(offsets.shape[0]):
            jx, jy, jz = sx + offsets[m, 0], sy + offsets[m, 1], sz + offsets[m, 2]
            if jx < 0 or jx >= nx or jy < 0 or jy >= ny or jz < 0 or jz >= nz:
                continue
            j = (jx * ny + jy) * nz + jz
            if done[j] or not free[j] or not _move_clear(free, shape, s, m, offsets, routes, route_counts):
                continue
            if p_ == GOAL_PARENT:
                tx, ty, tz = _to_box(goal_low, goal_high, float(jx), float(jy), float(jz))
                nd = cell_m * math.sqrt((jx - tx) ** 2 + (jy - ty) ** 2 + (jz - tz) ** 2)
            else:
                nd = dist[p_] + cell_m * math.sqrt((jx - px) ** 2 + (jy - py) ** 2 + (jz - pz) ** 2)
            if nd < dist[j]:
                dist[j] = nd
                parent[j] = p_
                heapq.heappush(heap, (nd, j))
    return dist, parent


@dataclass(frozen=True)
class Occupancy:
    """The grid over a workspace and which of its nodes are free (static obstacles grown)."""

    origin_m: np.ndarray
    shape: tuple[int, int, int]
    grid: PathGrid
    free: np.ndarray
    """(nx, ny, nz) bool."""

    def points(self, index: np.ndarray) -> np.ndarray:
        """ENU positions (m) of nodes given as (..., 3) integer indices."""
        return self.origin_m + index * self.grid.cell_m

    def free_at(self, position) -> bool:
        """Whether the node nearest to `position` (ENU) is free; False outside the grid."""
        index = np.rint((np.asarray(position, float) - self.origin_m) / self.grid.cell_m).astype(int)
        if np.any(index < 0) or np.any(index >= np.array(self.shape)):
            return False
        return bool(self.free[tuple(index)])


def _grid_shape(workspace: Workspace, cell_m: float) -> tuple[int, int, int]:
    size = np.asarray(workspace.max_m, float) - np.asarray(workspace.min_m, float)
    return tuple(max(2, int(math.floor(s / cell_m + 1e-9)) + 1) for s in size)  # type: ignore[return-value]


_client: int | None = None


def _probe_client() -> int:
    """The private DIRECT client the occupancy is probed on (one per process, reused)."""
    global _client
    if _client is None or not p.isConnected(physicsClientId=_client):
        _client = p.connect(p.DIRECT)
    return _client


def occupancy(workspace: Workspace, obstacles: Sequence[ObstaclePlacement], grid: PathGrid) -> Occupancy:
    """Free nodes of the grid over `workspace` around the static `obstacles` (not cached)."""
    shape = _grid_shape(workspace, grid.cell_m)
    if math.prod(shape) > MAX_NODES:
        raise ValueError(f"a path-distance grid of {shape[0]} x {shape[1]} x {shape[2]} nodes (cell_m "
                         f"{grid.cell_m:g}) is too large (at most {MAX_NODES}); use a larger cell_m")
    origin = np.asarray(workspace.min_m, float)
    free = np.ones(shape, dtype=bool)
    statics = [o for o in obstacles if not o.spec.dynamic]
    if statics:
        cid = _probe_client()
        p.resetSimulation(physicsClientId=cid)
        radius = max(grid.clearance_m, 1e-3)
        probe = p.createCollisionShape(p.GEOM_SPHERE, radius=radius, physicsClientId=cid)
        upper = np.array(shape) - 1
        for o in statics:
            body = create_obstacle(cid, o.shape, o.position_m, o.yaw_rad, o.spec.color_rgba)
            lo, hi = (np.asarray(c, float) for c in p.getAABB(body, physicsClientId=cid))
            first = np.clip(np.ceil((lo - radius - origin) / grid.cell_m - 1e-9), 0, upper).astype(int)
            last = np.clip(np.floor((hi + radius - origin) / grid.cell_m + 1e-9), 0, upper).astype(int)
            if np.any(hi + radius < origin) or np.any(lo - radius > origin + upper * grid.cell_m):
                continue  # wholly outside the workspace
            index = np.stack(np.meshgrid(*(np.arange(a, b + 1) for a, b in zip(first, last, strict=True)),
                                         indexing="ij"), axis=-1).reshape(-1, 3)
            index = index[free[index[:, 0], index[:, 1], index[:, 2]]]
            for node, point in zip(index.tolist(), (origin + index * grid.cell_m).tolist(), strict=True):
                if p.getClosestPoints(body, -1, 0.0, collisionShapeB=probe, collisionShapePositionB=point,
                                      physicsClientId=cid):
                    free[tuple(node)] = False
        p.resetSimulation(physicsClientId=cid)
    return Occupancy(origin, shape, grid, free)


class Unreachable(ValueError):
    """No free node leads to the goal region (the caller names the scenario)."""


@kernel(_sight, _to_box)
def _query(field: np.ndarray, parent: np.ndarray, free: np.ndarray, shape: np.ndarray, origin: np.ndarray,
           cell_m: float, point: np.ndarray, goal_low: np.ndarray, goal_high: np.ndarray) -> float:
    """Path length (m) from a point: the least over the reachable corners k of its cell of
    field[k] + |point - k|, and of field[q] + |point - q| for the parents q of those corners in
    the point's sight (the goal box itself: the straight distance to it); inf when no corner is
    reachable."""
    ny, nz = shape[1], shape[2]
    gx, gy, gz = (point[0] - origin[0]) / cell_m, (point[1] - origin[1]) / cell_m, (point[2] - origin[2]) / cell_m
    bx = min(max(int(math.floor(gx)), 0), shape[0] - 2)
    by = min(max(int(math.floor(gy)), 0), ny - 2)
    bz = min(max(int(math.floor(gz)), 0), nz - 2)
    best = np.inf
    tried = np.full(8, -3, dtype=np.int64)
    for c in range(8):
        ix, iy, iz = bx + (c >> 2), by + ((c >> 1) & 1), bz + (c & 1)
        k = (ix * ny + iy) * nz + iz
        if not math.isfinite(field[k]):
            continue
        best = min(best, field[k] + cell_m * math.sqrt((ix - gx) ** 2 + (iy - gy) ** 2 + (iz - gz) ** 2))
        q = parent[k]
        seen_before = False
        for t in range(c):
            seen_before = seen_before or tried[t] == q
        tried[c] = q
        if seen_before:
            continue
        if q == GOAL_PARENT:
            tx, ty, tz = _to_box(goal_low, goal_high, gx, gy, gz)
            if _sight(free, shape, gx, gy, gz, tx, ty, tz):
                best = min(best, cell_m * math.sqrt((tx - gx) ** 2 + (ty - gy) ** 2 + (tz - gz) ** 2))
        elif q >= 0:
            qx, qy, qz = q // (ny * nz), (q // nz) % ny, q % nz
            length = field[q] + cell_m * math.sqrt((qx - gx) ** 2 + (qy - gy) ** 2 + (qz - gz) ** 2)
            if length < best and _sight(free, shape, gx, gy, gz, float(qx), float(qy), float(qz)):
                best = length
    return best


class PathField:
    """Path distance to one goal region over one occupancy (see the module docstring)."""

    def __init__(self, occ: Occupancy, goal: GoalPlacement) -> None:
        self.occupancy = occ
        self.goal = goal
        flat_free = occ.free.reshape(-1)
        low = (np.asarray(goal.center_m, float) - np.asarray(goal.size_m, float) / 2.0 - occ.origin_m)
        high = low + np.asarray(goal.size_m, float)
        self._free = flat_free
        self.field, self._parent = _path_lengths(
            flat_free, np.array(occ.shape, dtype=np.int64), low / occ.grid.cell_m, high / occ.grid.cell_m,
            _OFFSETS, _LENGTHS, _ROUTES, _ROUTE_COUNTS, float(occ.grid.cell_m))
        if not np.isfinite(self.field).any():
            raise Unreachable(f"goal {goal.name!r} lies inside obstacles grown by the clearance")
        index = np.indices(occ.shape).reshape(3, -1).T
        reachable = np.isfinite(self.field)
        self._reachable_points = occ.points(index[reachable])
        self._reachable_values = self.field[reachable]
        self._free_points = occ.points(index[flat_free])
        self._free_values = self.field[flat_free]
        self._shape = np.array(occ.shape, dtype=np.int64)
        self._goal_low, self._goal_high = low / occ.grid.cell_m, high / occ.grid.cell_m

    def distance(self, position) -> float:
        """Path length (m) from `position` (ENU) to the goal region (see the module docstring)."""
        point = np.asarray(position, dtype=float)
        occ = self.occupancy
        best = _query(self.field, self._parent, self._free, self._shape, occ.origin_m, occ.grid.cell_m, point,
                      self._goal_low, self._goal_high)
        if math.isfinite(best):
            return best
        nearest = int(np.argmin(np.sum((self._reachable_points - point) ** 2, axis=1)))
        return float(self._reachable_values[nearest]
                     + np.linalg.norm(self._reachable_points[nearest] - point))

    def reaches(self, position) -> bool:
        """Whether the free node nearest to `position` has a path to the goal region."""
        if self._free_points.shape[0] == 0:
            return False
        point = np.asarray(position, dtype=float)
        nearest = int(np.argmin(np.sum((self._free_points - point) ** 2, axis=1)))
        return bool(np.isfinite(self._free_values[nearest]))


_occupancies: OrderedDict[tuple, Occupancy] = OrderedDict()
_fields: OrderedDict[tuple, PathField] = OrderedDict()


def _remember(cache: OrderedDict, key: tuple, value):
    cache[key] = value
    while len(cache) > CACHE_SIZE:
        cache.popitem(last=False)
    return value


def path_field(workspace: Workspace, obstacles: Sequence[ObstaclePlacement], goal: GoalPlacement,
               grid: PathGrid = PathGrid()) -> PathField:
    """The path field to `goal` around the static `obstacles`, cached by layout: the same
    workspace, grid, static obstacle shapes and poses and goal box give the same object back.
    Raises `Unreachable` when no free node is within a cell of the goal box."""
    statics = tuple((o.shape, tuple(o.position_m), float(o.yaw_rad)) for o in obstacles if not o.spec.dynamic)
    occ_key = (workspace.min_m, workspace.max_m, grid, statics)
    occ = _occupancies.get(occ_key)
    if occ is None:
        occ = _remember(_occupancies, occ_key, occupancy(workspace, obstacles, grid))
    else:
        _occupancies.move_to_end(occ_key)
    field_key = (occ_key, tuple(goal.center_m), tuple(goal.size_m))
    found = _fields.get(field_key)
    if found is not None and found.occupancy is occ:
        _fields.move_to_end(field_key)
        return found
    return _remember(_fields, field_key, PathField(occ, goal))
