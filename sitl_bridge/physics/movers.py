"""Kinematic movers for dynamic obstacles: where an obstacle is, which way it faces, how fast.

Both movers advance by a fixed time step and face their direction of motion (ENU yaw; random
legs also pitch along a climbing/descending leg). They are seeded through `reset(rng)`.
"""

from __future__ import annotations

import math

import numpy as np

from sitl_bridge.world.schema import PatrolMover, RandomLegsMover, Vec3


class Pose:
    """A mover's output for one step (ENU): position, facing (yaw, pitch) and velocity."""

    __slots__ = ("position_m", "yaw_rad", "pitch_rad", "velocity_m_s")

    def __init__(self, position_m: Vec3, yaw_rad: float, pitch_rad: float, velocity_m_s: Vec3) -> None:
        self.position_m = position_m
        self.yaw_rad = yaw_rad
        self.pitch_rad = pitch_rad
        self.velocity_m_s = velocity_m_s


class Patrol:
    """Back and forth along a polyline at constant speed (a pedestrian).

    Starts at the first point, or with `spec.random_start` at a uniformly drawn distance along
    the out-and-back route (so half the draws start on the way back).
    """

    def __init__(self, spec: PatrolMover) -> None:
        self.spec = spec
        # the out-and-back route as one closed list of segments
        points = list(spec.points_m)
        route = points + points[-2::-1]
        self._segments: list[tuple[Vec3, Vec3, float]] = []
        for a, b in zip(route, route[1:], strict=False):
            length = math.dist(a, b)
            if length > 1e-9:
                self._segments.append((a, b, length))
        self._cycle_m = sum(s[2] for s in self._segments)
        self._distance_m = 0.0
        # the simulation asks for the pose more than once per physics step: computed once
        self._pose: Pose | None = None

    @property
    def speed_m_s(self) -> float:
        return self.spec.speed_m_s

    def reset(self, rng: np.random.Generator) -> None:
        # Draw only with random_start: the shared mover stream (and so every other mover of
        # the existing worlds) stays as it was.
        self._distance_m = float(rng.uniform(0.0, self._cycle_m)) if self.spec.random_start else 0.0
        self._pose = None

    def pose(self) -> Pose:
        """Where the mover is now."""
        if self._pose is None:
            self._pose = self._compute_pose()
        return self._pose

    def _compute_pose(self) -> Pose:
        s = self._distance_m
        index = 0
        while index < len(self._segments) - 1 and s > self._segments[index][2]:
            s -= self._segments[index][2]
            index += 1
        a, b, length = self._segments[index]
        t = min(s / length, 1.0)
        position = (a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]), a[2] + t * (b[2] - a[2]))
        v = self.spec.speed_m_s / length
        velocity = ((b[0] - a[0]) * v, (b[1] - a[1]) * v, (b[2] - a[2]) * v)
        return Pose(position, math.atan2(velocity[1], velocity[0]), 0.0, velocity)

    def advance(self, dt_s: float) -> None:
        """Move on by dt."""
        if self._cycle_m > 0.0:
            self._distance_m = (self._distance_m + self.spec.speed_m_s * dt_s) % self._cycle_m
            self._pose = None


class RandomLegs:
    """Straight legs at constant speed to uniformly random points in a cuboid (a bird)."""

    def __init__(self, spec: RandomLegsMover, start_m: Vec3) -> None:
        self.spec = spec
        lo, hi = spec.min_m, spec.max_m
        self._start = tuple(min(max(s, low), high) for s, low, high in zip(start_m, lo, hi, strict=True))
        self._rng: np.random.Generator | None = None
        self._position: Vec3 = self._start  # type: ignore[assignment]
        self._target: Vec3 = self._start  # type: ignore[assignment]
        self._velocity: Vec3 = (0.0, 0.0, 0.0)
        self._pose: Pose | None = None  # as Patrol's: computed once per physics step

    @property
    def speed_m_s(self) -> float:
        return self.spec.speed_m_s

    def reset(self, rng: np.random.Generator) -> None:
        self._rng = rng
        self._position = self._start  # type: ignore[assignment]
        self._pose = None
        self._new_leg()

    def _new_leg(self) -> None:
        assert self._rng is not None
        lo, hi = self.spec.min_m, self.spec.max_m
        for _ in range(100):  # avoid a zero-length leg
            target = tuple(float(x) for x in self._rng.uniform(lo, hi))
            if math.dist(target, self._position) > 1e-3:
                break
        self._target = target  # type: ignore[assignment]
        d = math.dist(target, self._position)
        k = self.spec.speed_m_s / d
        self._velocity = tuple((t - p) * k for t, p in zip(target, self._position, strict=True))  # type: ignore[assignment]

    def pose(self) -> Pose:
        """Where the mover is now."""
        if self._pose is None:
            vx, vy, vz = self._velocity
            self._pose = Pose(self._position, math.atan2(vy, vx), math.atan2(vz, math.hypot(vx, vy)),
                              self._velocity)
        return self._pose

    def advance(self, dt_s: float) -> None:
        """Move on by dt; at the leg's end start a new leg with the remaining time."""
        self._pose = None
        remaining = dt_s
        for _ in range(10):
            d = math.dist(self._target, self._position)
            step = self.spec.speed_m_s * remaining
            if step < d:
                k = step / d
                (px, py, pz), (tx, ty, tz) = self._position, self._target
                self._position = (px + (tx - px) * k, py + (ty - py) * k, pz + (tz - pz) * k)
                return
            self._position = self._target
            remaining -= d / self.spec.speed_m_s
            self._new_leg()


def make_mover(spec: PatrolMover | RandomLegsMover, start_m: Vec3) -> Patrol | RandomLegs:
    """The mover for an obstacle's `mover:` spec."""
    if isinstance(spec, PatrolMover):
        return Patrol(spec)
    return RandomLegs(spec, start_m)
