"""The thesis's action table as NED velocities (no sockets)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from sitl_bridge.client.actions import NUM_ACTIONS, Action, action_velocity_ned


@pytest.mark.parametrize(
    ("code", "expected"),
    [
        (0, (0, 1, 0)),    # east = +E
        (1, (0, -1, 0)),   # west
        (2, (-1, 0, 0)),   # south = -N
        (3, (1, 0, 0)),    # north
        (4, (0, 0, 1)),    # down = +D
        (5, (0, 0, -1)),   # up
        (7, (0, 0, 0)),    # hover
    ],
)
def test_fixed_directions_are_unit_ned_vectors(code: int, expected: tuple[int, int, int]) -> None:
    np.testing.assert_allclose(action_velocity_ned(code), expected)
    np.testing.assert_allclose(action_velocity_ned(code, speed_m_s=2.0), np.multiply(expected, 2.0))


def test_eight_actions() -> None:
    assert NUM_ACTIONS == 8
    assert [a.value for a in Action] == list(range(8))


def test_toward_goal_needs_positions() -> None:
    with pytest.raises(ValueError, match="goal"):
        action_velocity_ned(Action.TOWARD_GOAL)


def test_toward_goal_at_goal_hovers() -> None:
    np.testing.assert_allclose(action_velocity_ned(6, position_ned_m=(1, 2, -3), goal_ned_m=(1, 2, -3)), 0.0)


@pytest.mark.parametrize("code", [-1, 8, 100])
def test_unknown_codes_are_rejected(code: int) -> None:
    with pytest.raises(ValueError):
        action_velocity_ned(code)


finite = st.floats(-100, 100, allow_nan=False)


@given(st.tuples(finite, finite, finite), st.tuples(finite, finite, finite), st.floats(0.1, 5.0))
def test_toward_goal_points_at_goal_with_the_given_speed(position, goal, speed) -> None:
    offset = np.subtract(goal, position)
    velocity = action_velocity_ned(6, position_ned_m=position, goal_ned_m=goal, speed_m_s=speed)
    if np.linalg.norm(offset) < 1e-3:
        np.testing.assert_allclose(velocity, 0.0)
        return
    assert np.linalg.norm(velocity) == pytest.approx(speed)
    assert float(np.dot(velocity, offset)) == pytest.approx(speed * np.linalg.norm(offset), rel=1e-9)
