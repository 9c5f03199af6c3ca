"""ORCA (rl/analysis/orca.py) on the paper's two-agent cases and its invariants, checked against
geometry computed here (cone legs, closest approach over the horizon) and a brute-force search."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sitl_bridge.rl.analysis.orca import Neighbour, orca_velocity

R = 0.6  # each agent's radius
TAU = 5.0


def closest_approach(p: np.ndarray, v_rel: np.ndarray, horizon: float) -> float:
    """Least distance over t in [0, horizon] between two agents `p` apart (other minus own)
    whose relative velocity (own minus other) is `v_rel`."""
    if v_rel @ v_rel < 1e-12:
        return float(np.linalg.norm(p))
    t = min(max(float(p @ v_rel) / float(v_rel @ v_rel), 0.0), horizon)
    return float(np.linalg.norm(p - t * v_rel))


def both_step(pa, va, pb, vb, *, share: float = 0.5, horizon: float = TAU):
    """Both agents run ORCA with their current velocity as preferred one."""
    pa, va, pb, vb = (np.asarray(x, dtype=float) for x in (pa, va, pb, vb))
    new_a, _ = orca_velocity(pa, va, va, R, 1.5, [Neighbour(pb, vb, R, share)], time_horizon=horizon)
    new_b, _ = orca_velocity(pb, vb, vb, R, 1.5, [Neighbour(pa, va, R, share)], time_horizon=horizon)
    return new_a, new_b


def test_head_on_both_sidestep_half_each_and_pass():
    d, speed = 10.0, 1.0
    va, vb = np.array([0.0, speed]), np.array([0.0, -speed])
    assert closest_approach(np.array([0.0, d]), va - vb, TAU) < 2 * R  # on a collision course
    new_a, new_b = both_step([0, 0], va, [0, d], vb)
    da, db = new_a - va, new_b - vb
    np.testing.assert_allclose(da, -db, atol=1e-12)  # reciprocal: equal and opposite
    # u: from the relative velocity (on the cone's axis) to the nearer leg, |v_rel| sin(half angle)
    assert np.linalg.norm(da) == pytest.approx(0.5 * 2 * speed * (2 * R) / d, rel=1e-9)
    assert abs(da[0]) > 0.9 * np.linalg.norm(da)  # mostly sideways
    assert np.sign(da[0]) == -np.sign(db[0])  # opposite world sides: each to the same hand
    assert closest_approach(np.array([0.0, d]), new_a - new_b, TAU) >= 2 * R - 1e-9


def test_crossing_at_right_angles_is_reciprocal_and_clears():
    pa, va = np.array([-5.0, 0.0]), np.array([1.0, 0.0])
    pb, vb = np.array([0.0, -5.0]), np.array([0.0, 1.0])
    assert closest_approach(pb - pa, va - vb, 6.0) < 2 * R
    new_a, new_b = both_step(pa, va, pb, vb, horizon=6.0)
    np.testing.assert_allclose(new_a - va, -(new_b - vb), atol=1e-12)
    assert np.linalg.norm(new_a - va) > 0.01
    assert closest_approach(pb - pa, new_a - new_b, 6.0) >= 2 * R - 1e-9


def test_agent_at_rest_takes_none_and_the_mover_takes_all():
    pa, va = np.array([0.0, 0.0]), np.array([0.0, 1.0])
    pb, vb = np.array([0.1, 4.0]), np.zeros(2)
    # the resting agent gives way to nothing: its share is 0, it stays at rest
    rest, _ = orca_velocity(pb, vb, vb, R, 1.5, [Neighbour(pa, va, R, responsibility=0.0)])
    np.testing.assert_allclose(rest, 0.0, atol=1e-12)
    # the mover, knowing the other will not move, takes the whole avoidance and clears it alone
    alone, _ = orca_velocity(pa, va, va, R, 1.5, [Neighbour(pb, vb, R, responsibility=1.0)])
    assert closest_approach(pb - pa, alone - vb, TAU) >= 2 * R - 1e-9
    # half of it (as if the other reciprocated) would still collide
    half, _ = orca_velocity(pa, va, va, R, 1.5, [Neighbour(pb, vb, R, responsibility=0.5)])
    assert closest_approach(pb - pa, half - vb, TAU) < 2 * R - 1e-3


def test_no_conflict_keeps_the_preferred_velocity():
    new, _ = orca_velocity(np.zeros(2), np.array([1.0, 0.0]), np.array([1.0, 0.0]), R, 1.5,
                           [Neighbour(np.array([0.0, 8.0]), np.array([1.0, 0.0]), R)])
    np.testing.assert_allclose(new, [1.0, 0.0])


def test_all_agents_running_orca_leave_every_truncated_velocity_obstacle():
    rng = np.random.default_rng(7)
    checked = 0
    for _ in range(200):
        n = int(rng.integers(2, 5))
        positions = rng.uniform(-4, 4, size=(n, 2))
        if min(np.linalg.norm(positions[i] - positions[j]) for i in range(n) for j in range(i)) < 2 * R + 0.2:
            continue
        velocities = rng.uniform(-1, 1, size=(n, 2))
        preferred = -positions / np.linalg.norm(positions, axis=1, keepdims=True)  # all toward the middle
        new, feasible = [], True
        for i in range(n):
            others = [Neighbour(positions[j], velocities[j], R) for j in range(n) if j != i]
            v, lines = orca_velocity(positions[i], velocities[i], preferred[i], R, 1.5, others)
            feasible &= all(line.violation(v) <= 1e-9 for line in lines)
            new.append(v)
        if not feasible:
            continue
        checked += 1
        for i in range(n):
            for j in range(i):
                assert closest_approach(positions[j] - positions[i], new[i] - new[j], TAU) >= 2 * R - 1e-6
    assert checked > 50


def test_the_chosen_velocity_is_the_nearest_allowed_one():
    rng = np.random.default_rng(3)
    grid = np.stack(np.meshgrid(np.linspace(-1.5, 1.5, 301), np.linspace(-1.5, 1.5, 301)), -1).reshape(-1, 2)
    grid = grid[np.linalg.norm(grid, axis=1) <= 1.5]
    compared = 0
    for _ in range(30):
        own = rng.uniform(-1, 1, 2)
        others = [Neighbour(rng.uniform(-5, 5, 2), rng.uniform(-1, 1, 2), R) for _ in range(3)]
        if min(np.linalg.norm(o.position) for o in others) < 2 * R + 0.2:
            continue
        preferred = rng.uniform(-1.5, 1.5, 2)
        v, lines = orca_velocity(np.zeros(2), own, preferred, R, 1.5, others)
        # det(direction, point - g) <= 0 for every line, over the whole grid at once
        allowed = grid[np.all([(line.direction[0] * (line.point[1] - grid[:, 1])
                                - line.direction[1] * (line.point[0] - grid[:, 0])) <= 0 for line in lines], axis=0)]
        if len(allowed) == 0:
            continue
        compared += 1
        assert all(line.violation(v) <= 1e-9 for line in lines)
        assert np.linalg.norm(v) <= 1.5 + 1e-9
        assert np.linalg.norm(v - preferred) <= np.min(np.linalg.norm(allowed - preferred, axis=1)) + 1e-9
    assert compared > 10


def test_infeasible_constraints_still_give_a_bounded_velocity():
    # boxed in by four agents closing fast: no velocity meets all half-planes
    others = [Neighbour(np.array([math.cos(a), math.sin(a)]) * 1.5, -np.array([math.cos(a), math.sin(a)]) * 1.5, R)
              for a in np.linspace(0, 2 * math.pi, 4, endpoint=False)]
    v, lines = orca_velocity(np.zeros(2), np.zeros(2), np.array([1.0, 0.0]), R, 1.0, others)
    assert np.all(np.isfinite(v)) and np.linalg.norm(v) <= 1.0 + 1e-9
    assert max(line.violation(v) for line in lines) > 0
