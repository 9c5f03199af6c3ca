"""The thesis's action table as NED velocities, and the client's waits on a simulated clock."""

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


def test_client_without_autopilot_times_out_and_releases_its_port() -> None:
    """Real MAVSDK listening on a free port with nobody sending: a clean wall-time timeout."""
    import socket

    from sitl_bridge.client import OffboardClient, SimTimeoutError

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    client = OffboardClient(0, url=f"udpin://127.0.0.1:{port}")
    with pytest.raises(SimTimeoutError, match="autopilot heartbeat"):
        client.connect(timeout_s=0.3)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as again:
        again.bind(("127.0.0.1", port))  # MAVSDK let go of it


def test_timed_legs_need_a_clock() -> None:
    from sitl_bridge.client import OffboardClient, OffboardClientError

    with pytest.raises(OffboardClientError, match="clock"):
        OffboardClient(0).fly_velocity_ned((1, 0, 0), 1.0)


class _CountingClock:
    """Simulated time that only moves when asked (what SimSession.run_for guarantees)."""

    def __init__(self) -> None:
        self.time_s = 0.0

    def run_for(self, seconds: float) -> None:
        self.time_s += seconds


def test_wait_until_advances_simulated_time_in_polls() -> None:
    from sitl_bridge.client import wait_until

    clock = _CountingClock()
    wait_until(lambda: clock.time_s >= 0.1, clock=clock, timeout_s=1.0, what="x", poll_s=0.04)
    assert clock.time_s == pytest.approx(0.12)  # three polls, then held


def test_wait_until_times_out_in_simulated_time_after_min_wall() -> None:
    import time

    from sitl_bridge.client import SimTimeoutError, wait_until

    clock = _CountingClock()
    with pytest.raises(SimTimeoutError, match="never: not observed within 0.2 s of simulated time"):
        wait_until(lambda: False, clock=clock, timeout_s=0.2, what="never", poll_s=0.04)
    assert clock.time_s == pytest.approx(0.2)
    start = time.monotonic()
    with pytest.raises(SimTimeoutError):
        wait_until(lambda: False, clock=clock, timeout_s=0.2, what="never", poll_s=0.04, min_wall_s=0.1)
    assert time.monotonic() - start >= 0.1


def test_discovering_the_autopilot_gets_the_commands_wall_time_floor(free_instance: int) -> None:
    """MAVSDK discovers an autopilot in its own threads, in wall time: a clock that runs the
    whole timeout at once must not end the discovery before `COMMAND_MIN_WALL_S` of wall time."""
    import time

    from sitl_bridge.client import OffboardClient, SimTimeoutError
    from sitl_bridge.ports import api_client_port

    client = OffboardClient(free_instance, clock=_CountingClock(),
                            url=f"udpin://127.0.0.1:{api_client_port(free_instance)}")  # nobody sends
    start = time.monotonic()
    with pytest.raises(SimTimeoutError, match="autopilot heartbeat"):
        client.connect(timeout_s=0.1)
    assert time.monotonic() - start >= OffboardClient.COMMAND_MIN_WALL_S
