"""Optimal reciprocal collision avoidance (ORCA) in the plane: van den Berg, Guy, Lin and Manocha,
"Reciprocal n-body collision avoidance" (ISRR 2009, Springer 2011).

One agent's step: for every neighbour, the truncated velocity obstacle VO^tau (the relative
velocities that collide within `time_horizon` s) gives `u`, the smallest change of the relative
velocity that leaves it; the agent takes `responsibility` of it (1/2 when the neighbour runs ORCA
too, 1 when it does not react, e.g. a drone at rest or one whose flight has ended), which makes a
half-plane of allowed velocities. The new velocity is the one nearest the preferred velocity
inside every half-plane and the speed disc (the paper's 2D linear program, section 5.2); when the
half-planes leave no room, the one that least violates the worst of them (the paper's 3D program,
section 5.3: the agents' safety is then traded evenly).

The geometry follows the authors' reference implementation (RVO2, Apache-2.0) line for line in
its arithmetic, not its code; only agents, no polygonal obstacles. Positions and velocities are
2-vectors (m, m/s); the caller chooses the plane (`rl.analysis.orca_policy`: the horizontal one).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

EPSILON = 1e-9


@dataclass(frozen=True)
class Neighbour:
    """Another agent as this one sees it (transponder data)."""

    position: np.ndarray
    velocity: np.ndarray
    radius: float
    responsibility: float = 0.5
    """Share of the avoidance this agent takes: 1/2 reciprocal, 1 for a neighbour that will not move aside."""


@dataclass(frozen=True)
class HalfPlane:
    """Allowed velocities v: those left of the directed line through `point` along `direction`,
    i.e. det(direction, point - v) <= 0."""

    point: np.ndarray
    direction: np.ndarray

    def violation(self, velocity: np.ndarray) -> float:
        """How far (m/s) `velocity` lies on the forbidden side (<= 0: allowed)."""
        return _det(self.direction, self.point - velocity)


def _det(a: np.ndarray, b: np.ndarray) -> float:
    return float(a[0] * b[1] - a[1] * b[0])


def _vec(x: float, y: float) -> np.ndarray:
    return np.array([x, y], dtype=float)


def orca_half_plane(position: np.ndarray, velocity: np.ndarray, radius: float, other: Neighbour,
                    time_horizon: float, time_step: float) -> HalfPlane:
    """The ORCA half-plane this agent gets from `other` (`time_step`: the decision period, used
    only when they already overlap: then leave the overlap within one step)."""
    rel_position = np.asarray(other.position, dtype=float) - position
    rel_velocity = velocity - np.asarray(other.velocity, dtype=float)
    dist_sq = float(rel_position @ rel_position)
    combined = radius + other.radius
    combined_sq = combined * combined
    if dist_sq > combined_sq:
        w = rel_velocity - rel_position / time_horizon  # from the cut-off disc's centre
        w_len_sq = float(w @ w)
        dot1 = float(w @ rel_position)
        if dot1 < 0.0 and dot1 * dot1 > combined_sq * w_len_sq:
            # nearest boundary point is on the cut-off disc (collision after tau is not counted)
            w_len = math.sqrt(w_len_sq)
            unit_w = w / w_len
            direction = _vec(unit_w[1], -unit_w[0])
            u = (combined / time_horizon - w_len) * unit_w
        else:
            # nearest boundary point is on a leg of the cone
            leg = math.sqrt(dist_sq - combined_sq)
            x, y = rel_position
            if _det(rel_position, w) > 0.0:  # left leg
                direction = _vec(x * leg - y * combined, x * combined + y * leg) / dist_sq
            else:  # right leg
                direction = -_vec(x * leg + y * combined, -x * combined + y * leg) / dist_sq
            u = float(rel_velocity @ direction) * direction - rel_velocity
    else:
        # already overlapping: leave the overlap within one time step
        w = rel_velocity - rel_position / time_step
        w_len = math.sqrt(float(w @ w))
        unit_w = w / w_len if w_len > EPSILON else _vec(1.0, 0.0)
        direction = _vec(unit_w[1], -unit_w[0])
        u = (combined / time_step - w_len) * unit_w
    return HalfPlane(velocity + other.responsibility * u, direction)


def _program1(lines: list[HalfPlane], k: int, radius: float, optimum: np.ndarray, direction_opt: bool
              ) -> np.ndarray | None:
    """The best point on line k within the disc and the half-planes before it (None: none)."""
    line = lines[k]
    dot = float(line.point @ line.direction)
    discriminant = dot * dot + radius * radius - float(line.point @ line.point)
    if discriminant < 0.0:
        return None  # the line misses the speed disc
    root = math.sqrt(discriminant)
    t_left, t_right = -dot - root, -dot + root
    for i in range(k):
        denominator = _det(line.direction, lines[i].direction)
        numerator = _det(lines[i].direction, line.point - lines[i].point)
        if abs(denominator) <= EPSILON:  # parallel lines
            if numerator < 0.0:
                return None
            continue
        t = numerator / denominator
        if denominator >= 0.0:
            t_right = min(t_right, t)
        else:
            t_left = max(t_left, t)
        if t_left > t_right:
            return None
    if direction_opt:
        t = t_right if float(optimum @ line.direction) > 0.0 else t_left
    else:
        t = min(max(float(line.direction @ (optimum - line.point)), t_left), t_right)
    return line.point + t * line.direction


def _program2(lines: list[HalfPlane], radius: float, optimum: np.ndarray, direction_opt: bool
              ) -> tuple[np.ndarray, int]:
    """The velocity nearest `optimum` (or farthest along it, `direction_opt`) in the disc and
    every half-plane, and the number of half-planes met (len(lines): all)."""
    if direction_opt:
        result = optimum * radius
    elif float(optimum @ optimum) > radius * radius:
        result = optimum / np.linalg.norm(optimum) * radius
    else:
        result = optimum.copy()
    for i, line in enumerate(lines):
        if line.violation(result) > 0.0:
            found = _program1(lines, i, radius, optimum, direction_opt)
            if found is None:
                return result, i
            result = found
    return result, len(lines)


def _program3(lines: list[HalfPlane], first_failed: int, radius: float, result: np.ndarray) -> np.ndarray:
    """No velocity meets every half-plane: the one minimising the largest violation."""
    distance = 0.0
    for i in range(first_failed, len(lines)):
        if lines[i].violation(result) > distance:
            projected: list[HalfPlane] = []
            for j in range(i):
                determinant = _det(lines[i].direction, lines[j].direction)
                if abs(determinant) <= EPSILON:
                    if float(lines[i].direction @ lines[j].direction) > 0.0:
                        continue  # same direction: j is no tighter
                    point = 0.5 * (lines[i].point + lines[j].point)
                else:
                    point = lines[i].point + (_det(lines[j].direction, lines[i].point - lines[j].point)
                                              / determinant) * lines[i].direction
                between = lines[j].direction - lines[i].direction
                projected.append(HalfPlane(point, between / np.linalg.norm(between)))
            candidate, met = _program2(projected, radius, _vec(-lines[i].direction[1], lines[i].direction[0]), True)
            if met == len(projected):
                result = candidate
            distance = lines[i].violation(result)
    return result


def orca_velocity(position: np.ndarray, velocity: np.ndarray, preferred: np.ndarray, radius: float,
                  max_speed: float, neighbours: list[Neighbour], *, time_horizon: float = 5.0,
                  time_step: float = 1.0) -> tuple[np.ndarray, list[HalfPlane]]:
    """The new velocity of an agent at `position` flying `velocity` that would like `preferred`,
    and the half-planes that bound it (one per neighbour, in order)."""
    position = np.asarray(position, dtype=float)
    velocity = np.asarray(velocity, dtype=float)
    lines = [orca_half_plane(position, velocity, radius, n, time_horizon, time_step) for n in neighbours]
    result, met = _program2(lines, max_speed, np.asarray(preferred, dtype=float), False)
    if met < len(lines):
        result = _program3(lines, met, max_speed, result)
    return result, lines
