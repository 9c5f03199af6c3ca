"""`Lidar`: body-fixed range rays for every vehicle, cast in one pybullet `rayTestBatch`.

Layout per vehicle (`LidarConfig`, from the world file): a horizontal ring (35 rays over 360
deg by default), an upward fan and a downward fan (6 rays over 90 deg each, in the body x-z
plane). Ray i of a group points at angle -fov/2 + (i + 0.5) fov / n: horizontal angles are
measured from forward, counter-clockwise (FLU yaw; with an odd count the middle ray points
forward), fan angles from straight up / down toward forward. Rays start at the body centre, so
they never see their own body (bullet does not report a ray leaving a convex shape). No hit ->
the maximum range, never inf/NaN. Scan on demand (e.g. once per env step): not every physics
step.
"""

from __future__ import annotations

import collections
import math
import operator
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from sitl_bridge.frames import quat_to_matrix_t
from sitl_bridge.jit import kernel
from sitl_bridge.physics.bullet import p
from sitl_bridge.physics.simulation import Simulation
from sitl_bridge.sensors.ray_reach import REACH_MARGIN_M, merge_hits, rays_to_cast
from sitl_bridge.world.schema import LidarConfig

__all__ = ["Lidar", "LidarConfig", "LidarScan", "ray_directions_flu", "ray_labels"]

_HIT_BODY = operator.itemgetter(0)  # rayTestBatch result: (body, link, fraction, position, normal)
_HIT_FRACTION = operator.itemgetter(2)


@dataclass
class LidarScan:
    """One vehicle's ranges (m, from the body centre; max range when nothing was hit)."""

    horizontal_m: np.ndarray
    up_m: np.ndarray
    down_m: np.ndarray
    near: bool        # some flagged ray is below config.near_m
    crash: bool       # some flagged ray is below config.crash_m
    min_m: float      # shortest flagged ray (max range when none)
    time_us: int = 0  # simulated time of the scan (extension of the contract)
    crash_by_vehicles: bool = False  # crash, and every flagged ray below crash distance hit a vehicle


def _fan(count: int, fov_deg: float) -> list[float]:
    fov = math.radians(fov_deg)
    return [-fov / 2.0 + fov * (i + 0.5) / count for i in range(count)]


STRAIGHT_DEG = 5
"""A ray within this many degrees of forward, backward, up or down is named plainly so."""


def ray_labels(config: LidarConfig) -> dict[str, tuple[str, ...]]:
    """Each ray's direction in words, per group, for rules a person reads: `ahead`, `30 deg left`,
    `behind`, `above`, `below, 38 deg ahead` (ahead = the body's forward)."""
    def horizontal(a: float) -> str:
        deg = round(math.degrees(a))
        if abs(deg) <= STRAIGHT_DEG:
            return "ahead"
        if abs(deg) >= 180 - STRAIGHT_DEG:
            return "behind"
        return f"{abs(deg)} deg {'left' if deg > 0 else 'right'}"  # FLU: +y is left

    def fan(where: str, b: float) -> str:
        deg = round(math.degrees(b))
        return where if abs(deg) <= STRAIGHT_DEG else f"{where}, {abs(deg)} deg {'ahead' if deg > 0 else 'back'}"

    return {"horizontal": tuple(horizontal(a) for a in _fan(config.horizontal_rays, config.horizontal_fov_deg)),
            "up": tuple(fan("above", b) for b in _fan(config.up_rays, config.up_fov_deg)),
            "down": tuple(fan("below", b) for b in _fan(config.down_rays, config.down_fov_deg))}


def ray_directions_flu(config: LidarConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit ray directions in body FLU for the horizontal ring, the up fan and the down fan."""
    horizontal = [(math.cos(a), math.sin(a), 0.0) for a in _fan(config.horizontal_rays, config.horizontal_fov_deg)]
    up = [(math.sin(b), 0.0, math.cos(b)) for b in _fan(config.up_rays, config.up_fov_deg)]
    down = [(math.sin(b), 0.0, -math.cos(b)) for b in _fan(config.down_rays, config.down_fov_deg)]
    return (np.array(horizontal).reshape(-1, 3), np.array(up).reshape(-1, 3), np.array(down).reshape(-1, 3))


@kernel()
def split_ranges(ranges: np.ndarray, a: int, b: int, flagged: np.ndarray,
                 no_flag_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """One vehicle's ranges as copies of its groups (`[:a]`, `[a:b]`, `[b:]`) and the shortest
    range of the `flagged` rays (`no_flag_m` when none is flagged)."""
    shortest = np.inf
    seen = False
    for k in range(ranges.shape[0]):
        if flagged[k]:
            seen = True
            shortest = min(shortest, ranges[k])
    return ranges[:a].copy(), ranges[a:b].copy(), ranges[b:].copy(), shortest if seen else no_flag_m


class Lidar:
    """Lidars of all vehicles of a simulation.

    Args:
        sim: the simulation whose vehicles carry the lidars.
        config: None -> each vehicle's `lidar:` from the world file; one `LidarConfig` -> the
            same for all vehicles; a sequence -> one per vehicle.
    """

    def __init__(self, sim: Simulation, config: LidarConfig | Sequence[LidarConfig] | None = None) -> None:
        self.sim = sim
        if config is None:
            configs = [v.lidar for v in sim.world.vehicles]
        elif isinstance(config, LidarConfig):
            configs = [config] * sim.num_vehicles
        else:
            configs = list(config)
        if len(configs) != sim.num_vehicles:
            raise ValueError(f"expected {sim.num_vehicles} lidar configs, got {len(configs)}")
        self.configs = tuple(configs)
        # per vehicle: directions scaled to range (FLU), and the group split points
        self._scaled: list[np.ndarray] = []
        self._splits: list[tuple[int, int]] = []
        self._flag_masks: list[np.ndarray] = []
        for c in self.configs:
            h, u, d = ray_directions_flu(c)
            self._scaled.append(np.vstack((h, u, d)) * c.range_m)
            self._splits.append((len(h), len(h) + len(u)))
            mask = np.concatenate([np.full(len(g), name in c.flag_groups)
                                   for name, g in (("horizontal", h), ("up", u), ("down", d))])
            self._flag_masks.append(mask)
        sizes = [len(scaled) for scaled in self._scaled]
        bounds = np.cumsum([0, *sizes])
        self._slices = [(int(bounds[i]), int(bounds[i + 1])) for i in range(len(sizes))]
        self._starts = np.zeros((int(bounds[-1]), 3))
        self._ends = np.zeros((int(bounds[-1]), 3))
        self._history: list[collections.deque[np.ndarray]] = [
            collections.deque(maxlen=c.filter_window) for c in self.configs]
        self._owners = np.repeat(np.arange(len(sizes), dtype=np.int64), sizes)  # the vehicle casting each ray
        self.prune = True
        """Cast only the rays that may hit something (`sensors.ray_reach`); False: every ray
        (the reference the pruned scan matches bit for bit)."""

    def reset(self) -> None:
        """Forget the moving-average history (call after `Simulation.reset`)."""
        for h in self._history:
            h.clear()

    def scan(self) -> list[LidarScan]:
        """Cast every vehicle's rays at the current simulation state, one batch for all (with
        `prune`, only the rays that may hit something: the others have the no-hit answer)."""
        starts, ends = self._starts, self._ends
        for i, scaled in enumerate(self._scaled):
            a, b = self._slices[i]
            position, q_wxyz = self.sim.pose(i)
            rotation = np.array(quat_to_matrix_t(q_wxyz)).reshape(3, 3)
            starts[a:b] = position
            np.matmul(scaled, rotation.T, out=ends[a:b])
            ends[a:b] += position
        fractions, bodies = self._cast(starts, ends)
        scans = []
        offset = 0
        for i, c in enumerate(self.configs):
            n = len(self._scaled[i])
            ranges = fractions[offset:offset + n] * c.range_m
            offset += n
            history = self._history[i]
            history.append(ranges)
            if len(history) > 1:
                ranges = np.mean(history, axis=0)
            scans.append(self._make_scan(c, ranges, i, bodies[offset - n:offset]))
        return scans

    def _cast(self, starts: np.ndarray, ends: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per ray: pybullet's hit fraction (1: no hit) and the body hit (-1: none)."""
        count = len(starts)
        if not count:
            return np.ones(0), np.full(0, -1, dtype=np.int64)
        cid = self.sim.client_id
        if not self.prune:
            results = p.rayTestBatch(starts, ends, physicsClientId=cid)  # reads numpy arrays directly
            return (np.fromiter(map(_HIT_FRACTION, results), dtype=float, count=count),
                    np.fromiter(map(_HIT_BODY, results), dtype=np.int64, count=count))
        # a vehicle's own box never counts for its rays: with one vehicle no vehicle box does
        boxes, box_owners = self.sim.body_boxes(vehicles=self.sim.num_vehicles > 1)
        cast, cast_starts, cast_ends = rays_to_cast(starts, ends, self._owners, boxes, box_owners, self.sim.has_ground,
                                                    REACH_MARGIN_M)
        n = len(cast)
        results = p.rayTestBatch(cast_starts, cast_ends, physicsClientId=cid) if n else ()
        return merge_hits(count, cast, np.fromiter(map(_HIT_FRACTION, results), dtype=float, count=n),
                          np.fromiter(map(_HIT_BODY, results), dtype=np.int64, count=n))

    def _make_scan(self, c: LidarConfig, ranges: np.ndarray, vehicle: int, bodies: np.ndarray) -> LidarScan:
        a, b = self._splits[vehicle]
        mask = self._flag_masks[vehicle]
        horizontal, up, down, min_m = split_ranges(ranges, a, b, mask, c.range_m)
        crash = min_m < c.crash_m
        # which drone a crash between drones is charged to depends on whether only drones caused it
        by_vehicles = crash and bool(np.all(np.isin(bodies[mask & (ranges < c.crash_m)], self.sim.vehicle_bodies)))
        return LidarScan(horizontal_m=horizontal, up_m=up, down_m=down, near=min_m < c.near_m, crash=crash,
                         min_m=float(min_m), time_us=self.sim.time_us, crash_by_vehicles=by_vehicles)
