"""End to end through real sockets: simulator -> HIL link -> stub autopilot -> MAVLink API ->
the real `mavsdk` package (v4 native binding) -> OffboardClient.

One session flies the whole thesis sequence; the tests run in order on it (module scope) so the
flight is flown once: connect, health, arm, takeoff, offboard, six directions, hold, land.
"""

from __future__ import annotations

import numpy as np
import pytest
from mavsdk.plugins.action import ActionError, RelayCommand
from test_session import pick_mavlink_instances

from sitl_bridge.client import Fleet, OffboardClient
from sitl_bridge.client.actions import Action, action_velocity_ned
from sitl_bridge.client.demo import DEMO_ACTIONS, fly_leg
from sitl_bridge.session import SimSession, default_world_path

TAKEOFF_ALT_M = 2.5


@pytest.fixture(scope="module")
def flight():
    """A running stub session at full speed with one connected MAVSDK client."""
    instance = pick_mavlink_instances(1)
    with SimSession(default_world_path(), autopilot="stub", speed_factor=0, instance_base=instance) as session:
        client = OffboardClient(instance, clock=session).connect()
        try:
            yield session, client
        finally:
            client.close()


def test_mavsdk_sees_a_healthy_px4(flight) -> None:
    session, client = flight
    assert client.autopilot_type() == "PX4"
    client.wait_healthy(timeout_s=30)
    health = client.health()
    assert health and all(health.values()), health
    assert not client.armed()
    assert not client.in_air()


def test_parameter_read_and_set_round_trip(flight) -> None:
    _, client = flight
    assert client.get_param_float("MIS_TAKEOFF_ALT") == pytest.approx(TAKEOFF_ALT_M)
    client.set_param_float("MPC_XY_CRUISE", 4.25)
    assert client.get_param_float("MPC_XY_CRUISE") == pytest.approx(4.25)
    original = client.get_param_int("COM_RC_IN_MODE")
    client.set_param_int("COM_RC_IN_MODE", original)
    assert client.get_param_int("COM_RC_IN_MODE") == original
    client.set_param_float("MPC_XY_CRUISE", 5.0)


def test_unknown_command_is_unsupported(flight) -> None:
    _, client = flight
    # DO_SET_RELAY has no meaning for the stub: it must ACK UNSUPPORTED, not time out.
    future = client.submit(client.action.set_relay, 0, RelayCommand.ON)
    with pytest.raises(Exception) as info:
        client.finish(future, "set relay")
    cause = info.value.__cause__
    assert isinstance(cause, ActionError) and cause.result.name == "UNSUPPORTED"


def test_arm_and_take_off(flight) -> None:
    session, client = flight
    client.arm()
    client.wait_until(client.armed, "armed", 2.0)
    altitude = client.takeoff(TAKEOFF_ALT_M)
    assert altitude == pytest.approx(TAKEOFF_ALT_M, abs=0.3)
    assert client.in_air()
    assert client.flight_mode() == "HOLD"
    truth_up_m = session.vehicle_state(0).position_enu_m[2]
    assert truth_up_m == pytest.approx(TAKEOFF_ALT_M, abs=0.4)


def test_offboard_mode_is_reported(flight) -> None:
    _, client = flight
    client.start_offboard()
    assert client.flight_mode() == "OFFBOARD"


@pytest.mark.parametrize("action", DEMO_ACTIONS, ids=lambda a: a.name.lower())
def test_velocity_step_moves_the_commanded_metre(flight, action: Action) -> None:
    session, client = flight
    t0 = session.time_s
    truth0 = session.vehicle_state(0).position_ned_m
    (leg,) = fly_leg(Fleet.of([client], clock=session), action)
    commanded = action_velocity_ned(action) * 1.0
    np.testing.assert_allclose(leg.commanded_ned_m, commanded)
    assert leg.error_m <= 0.25, leg.line()
    # MAVSDK's view agrees with the simulator's ground truth.
    truth = session.vehicle_state(0).position_ned_m - truth0
    np.testing.assert_allclose(leg.achieved_ned_m, truth, atol=0.15)
    assert client.flight_mode() == "OFFBOARD"
    assert session.time_s - t0 == pytest.approx(3.0, abs=1e-6)  # 1 s leg + 2 s settle, exactly


def test_hold_then_land_and_disarm(flight) -> None:
    _, client = flight
    client.hold()
    assert client.flight_mode() == "HOLD"
    client.finish(client.request_land(), "land")
    client.wait_until(lambda: client.flight_mode() == "LAND", "LAND mode", 3.0)
    client.wait_until(client.landed_and_disarmed, "landed and disarmed", 60.0)
    assert not client.armed() and not client.in_air()


def test_stub_processes_get_the_speed_factor_and_parameter_overrides() -> None:
    """`autopilot="stub-process"`: each stub is `sitl-bridge stub -i N`, configured like in-process."""
    instance = pick_mavlink_instances(1)
    with SimSession("empty", autopilot="stub-process", speed_factor=0, instance_base=instance,
                    params={"MIS_TAKEOFF_ALT": 3.0}) as session, \
            OffboardClient(instance, clock=session) as client:
        assert client.autopilot_type() == "PX4"
        assert client.get_param_float("COM_OF_LOSS_T") == pytest.approx(30.0)
        assert client.get_param_float("MIS_TAKEOFF_ALT") == pytest.approx(3.0)
        client.wait_healthy(timeout_s=30)
        assert not session.lockstep.pumps  # nothing in-process
