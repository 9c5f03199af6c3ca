"""Closed-loop flight of the StubAutopilot with the real pybullet physics and sensors (no sockets)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sitl_bridge.autopilot.stub import CommandResult, LandedState, MainMode, ParamTable, custom_mode
from sitl_bridge.autopilot.stub.harness import StubHarness
from sitl_bridge.autopilot.stub.modes import HOLD, LAND, OFFBOARD, RTL
from sitl_bridge.world.loader import load_world

WORLD = load_world(Path(__file__).resolve().parents[1] / "worlds" / "empty.yaml")


def mode_of(harness: StubHarness) -> tuple[int, int]:
    c = harness.autopilot.commander
    return (c.main_mode, c.sub_mode)


@pytest.fixture
def flying() -> StubHarness:
    """Hovering at the takeoff altitude in OFFBOARD with a zero velocity setpoint."""
    with StubHarness(WORLD, seed=3) as harness:
        harness.take_off()
        ap = harness.autopilot
        ap.set_velocity_setpoint_ned((0.0, 0.0, 0.0))
        assert ap.set_mode(MainMode.OFFBOARD, 0) is CommandResult.ACCEPTED
        harness.fly_velocity((0.0, 0.0, 0.0), 2.0)
        yield harness


@pytest.mark.parametrize("ground_truth", [False, True])
def test_takeoff_climbs_to_mis_takeoff_alt_then_holds(ground_truth: bool) -> None:
    with StubHarness(WORLD, seed=1, ground_truth_estimate=ground_truth) as harness:
        ap = harness.autopilot
        start = harness.position_ned_m.copy()
        harness.take_off()
        harness.run_for(4.0)
        altitude = start[2] - harness.position_ned_m[2]
        assert altitude == pytest.approx(2.5, abs=0.3)
        assert mode_of(harness) == HOLD
        assert ap.custom_mode == 50593792   # AUTO.LOITER as MAVSDK decodes HOLD
        assert ap.landed_state is LandedState.IN_AIR
        drift = np.linalg.norm(harness.position_ned_m[:2] - start[:2])
        assert drift < 0.3


def test_hover_holds_position_without_setpoints() -> None:
    with StubHarness(WORLD, seed=2) as harness:
        harness.take_off()
        harness.run_for(3.0)
        held = harness.position_ned_m.copy()
        harness.run_for(10.0)
        assert np.linalg.norm(harness.position_ned_m - held) < 0.3


def test_arming_needs_an_aligned_position_estimate() -> None:
    with StubHarness(WORLD, seed=4) as harness:
        ap = harness.autopilot
        harness.run_for(0.004)
        assert ap.arm() is CommandResult.DENIED
        harness.run_for(1.0)   # GPS origin set, attitude still aligning (like EKF2)
        assert ap.arm() is CommandResult.DENIED
        assert not ap.armed
        harness.run_for(2.5)
        assert ap.arm() is CommandResult.ACCEPTED


# north, south, east, west, up, down as NED velocity
DIRECTIONS = {
    "north": (1.0, 0.0, 0.0), "south": (-1.0, 0.0, 0.0), "east": (0.0, 1.0, 0.0),
    "west": (0.0, -1.0, 0.0), "up": (0.0, 0.0, -1.0), "down": (0.0, 0.0, 1.0),
}


@pytest.mark.parametrize("name", list(DIRECTIONS))
def test_one_second_velocity_step_moves_like_px4(flying: StubHarness, name: str) -> None:
    """1 m/s for 1 s from hover: PX4's velocity loop lags, so the step moves less than 1 m
    (PX4 SIH: ~0.3-0.4 m horizontal, ~0.7-0.85 m vertical) and the vehicle coasts after."""
    direction = np.array(DIRECTIONS[name])
    start = flying.position_ned_m.copy()
    flying.fly_velocity(tuple(direction), 1.0)
    step = flying.position_ned_m - start
    along = float(step @ direction)
    if direction[2] == 0.0:
        assert 0.3 <= along <= 0.65
    else:
        assert 0.6 <= along <= 1.0
    flying.fly_velocity((0.0, 0.0, 0.0), 3.0)
    total = flying.position_ned_m - start
    assert float(total @ direction) == pytest.approx(1.0, abs=0.25)
    across = total - (total @ direction) * direction
    assert np.linalg.norm(across) < 0.2
    assert mode_of(flying) == OFFBOARD


def test_position_setpoint_in_offboard(flying: StubHarness) -> None:
    ap = flying.autopilot
    target = np.array(ap.estimate.position_ned_m) + np.array((2.0, -1.0, -0.5))
    ap.set_position_setpoint_ned(tuple(target))
    for _ in range(8):   # refresh like a client would, faster than COM_OF_LOSS_T
        flying.run_for(0.5)
        ap.set_position_setpoint_ned(tuple(target))
    assert np.linalg.norm(np.array(ap.estimate.position_ned_m) - target) < 0.3


def test_offboard_needs_a_recent_setpoint() -> None:
    with StubHarness(WORLD, seed=5) as harness:
        harness.take_off()
        ap = harness.autopilot
        assert ap.set_mode(MainMode.OFFBOARD, 0) is CommandResult.TEMPORARILY_REJECTED
        ap.set_velocity_setpoint_ned((0.0, 0.0, 0.0))
        harness.run_for(1.5)   # older than COM_OF_LOSS_T
        assert ap.set_mode(MainMode.OFFBOARD, 0) is CommandResult.TEMPORARILY_REJECTED
        ap.set_velocity_setpoint_ned((0.0, 0.0, 0.0))
        assert ap.set_mode(MainMode.OFFBOARD, 0) is CommandResult.ACCEPTED


@pytest.mark.parametrize(("action", "expected"), [(5, HOLD), (4, LAND), (0, HOLD), (3, RTL)])
def test_offboard_loss_failsafe_in_simulated_time(action: int, expected: tuple[int, int]) -> None:
    params = ParamTable()
    params.set("COM_OBL_RC_ACT", action)
    loss_s = params["COM_OF_LOSS_T"]
    with StubHarness(WORLD, seed=6, params=params) as harness:
        harness.take_off()
        ap = harness.autopilot
        ap.set_velocity_setpoint_ned((0.5, 0.0, 0.0))
        assert ap.set_mode(MainMode.OFFBOARD, 0) is CommandResult.ACCEPTED
        harness.run_for(loss_s - 0.1)
        assert mode_of(harness) == OFFBOARD
        harness.run_for(0.2)
        assert mode_of(harness) == expected
        assert ap.commander.failsafe_active
        assert any("offboard" in text.lower() for _, text in ap.commander.status_texts)


def test_land_touches_down_and_disarms_itself() -> None:
    with StubHarness(WORLD, seed=7) as harness:
        ap = harness.autopilot
        ground_z = harness.position_ned_m[2]
        harness.take_off()
        assert ap.land() is CommandResult.ACCEPTED
        assert ap.custom_mode == custom_mode(*LAND)
        harness.run_for(1.0)
        assert ap.landed_state is LandedState.LANDING
        assert harness.run_for(15.0, until=lambda: ap.landed_state is LandedState.ON_GROUND)
        assert ap.armed
        assert abs(harness.position_ned_m[2] - ground_z) < 0.1
        disarm_after_s = ap.params["COM_DISARM_LAND"]
        assert harness.run_for(disarm_after_s + 0.5, until=lambda: not ap.armed)
        assert ap.last_command.armed is False
        assert ap.last_command.controls == (0.0, 0.0, 0.0, 0.0)


def test_disarm_in_the_air_needs_force() -> None:
    with StubHarness(WORLD, seed=8) as harness:
        harness.take_off()
        ap = harness.autopilot
        assert ap.disarm() is CommandResult.DENIED
        assert ap.armed
        assert ap.disarm(force=True) is CommandResult.ACCEPTED
        assert not ap.armed


def test_armed_on_the_ground_idles_and_disarms_after_preflight_timeout() -> None:
    params = ParamTable()
    params.set("COM_DISARM_PRFLT", 3.0)
    with StubHarness(WORLD, seed=9, params=params) as harness:
        ap = harness.autopilot
        assert harness.run_for(5.0, until=lambda: ap.arm() is CommandResult.ACCEPTED)
        harness.run_for(1.0)
        assert ap.armed and ap.landed_state is LandedState.ON_GROUND
        assert ap.last_command.controls == (0.0, 0.0, 0.0, 0.0) and ap.last_command.armed
        assert harness.run_for(2.5, until=lambda: not ap.armed)


def test_return_to_launch_flies_home_and_lands() -> None:
    params = ParamTable()
    params.set("RTL_RETURN_ALT", 4.0)
    with StubHarness(WORLD, seed=10, params=params) as harness:
        ap = harness.autopilot
        home = harness.position_ned_m.copy()
        harness.take_off()
        ap.set_velocity_setpoint_ned((0.0, 0.0, 0.0))
        assert ap.set_mode(MainMode.OFFBOARD, 0) is CommandResult.ACCEPTED
        harness.fly_velocity((1.5, -1.0, 0.0), 2.0)
        assert ap.return_to_launch() is CommandResult.ACCEPTED
        assert harness.run_for(4.0, until=lambda: -harness.position_ned_m[2] > 3.5)   # climbs first
        assert harness.run_for(40.0, until=lambda: not ap.armed)
        assert np.linalg.norm(harness.position_ned_m[:2] - home[:2]) < 0.5
        assert abs(harness.position_ned_m[2] - home[2]) < 0.1
