"""Hostile or absurd MAVLink commands over real UDP: each is answered (ACK or PARAM_VALUE),
nothing non-finite reaches the controllers, and the vehicle keeps flying."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
from test_stub_api import HOLD_CUSTOM_MODE, command_long, d, of_type, vehicle  # noqa: F401 (fixture)

INF = float("inf")


def _airborne(vehicle_fixture):  # noqa: ANN001
    harness, api, peer, advance = vehicle_fixture
    peer.send(command_long(d.MAV_CMD_NAV_TAKEOFF))
    assert peer.receive(of_type("COMMAND_ACK")).result == d.MAV_RESULT_ACCEPTED
    peer.send(command_long(d.MAV_CMD_COMPONENT_ARM_DISARM, 1.0))
    assert peer.receive(of_type("COMMAND_ACK")).result == d.MAV_RESULT_ACCEPTED
    advance(6.0)
    assert -harness.autopilot.estimate.position_ned_m[2] > 2.0
    return harness, api, peer, advance


def _reposition(api, lat_deg: float, lon_deg: float, alt_m: float, yaw_deg: float):  # noqa: ANN001
    # COMMAND_LONG: lat/lon as float degrees, so +-inf can be sent as they would arrive
    return d.MAVLink_command_long_message(api.system_id, 1, d.MAV_CMD_DO_REPOSITION, 0,
                                          -1.0, 1.0, 0.0, yaw_deg, lat_deg, lon_deg, alt_m)


def _still_flying(harness, advance, seconds: float = 3.0) -> None:  # noqa: ANN001
    start = np.array(harness.autopilot.estimate.position_ned_m)
    advance(seconds)
    state = harness.sim.state(0) if hasattr(harness, "sim") else None
    now = np.array(harness.autopilot.estimate.position_ned_m)
    assert np.all(np.isfinite(now))
    assert -now[2] > 1.5, f"vehicle fell from {-start[2]:.1f} m to {-now[2]:.1f} m"
    assert harness.autopilot.armed
    if state is not None:
        assert np.all(np.isfinite(state.position_enu_m))


@pytest.mark.parametrize(("lat", "lon", "yaw"), [(math.nan, math.nan, INF), (INF, math.nan, math.nan),
                                                 (math.nan, -INF, -INF), (INF, -INF, INF)],
                         ids=["yaw=inf", "lat=+inf", "lon=-inf", "all-inf"])
def test_reposition_with_infinite_fields_keeps_the_current_value(vehicle, lat, lon, yaw) -> None:  # noqa: F811
    harness, api, peer, advance = _airborne(vehicle)
    altitude = harness.autopilot.estimate.origin[2] + 3.0
    peer.send(_reposition(api, lat, lon, altitude, yaw))
    ack = peer.receive(lambda m: m.get_type() == "COMMAND_ACK" and m.command == d.MAV_CMD_DO_REPOSITION)
    assert ack.result == d.MAV_RESULT_ACCEPTED  # as PX4: a non-finite field means "unchanged"
    _still_flying(harness, advance)
    assert harness.autopilot.custom_mode == HOLD_CUSTOM_MODE


def test_reposition_off_the_globe_is_denied(vehicle) -> None:  # noqa: F811
    harness, api, peer, advance = _airborne(vehicle)
    peer.send(_reposition(api, 1e9, 8.5, math.nan, math.nan))
    ack = peer.receive(lambda m: m.get_type() == "COMMAND_ACK" and m.command == d.MAV_CMD_DO_REPOSITION)
    assert ack.result == d.MAV_RESULT_DENIED
    _still_flying(harness, advance)


def test_absurd_param_set_is_bounded_to_px4s_range(vehicle) -> None:  # noqa: F811
    harness, api, peer, advance = _airborne(vehicle)
    table = harness.autopilot.params
    for name, value, expected in ((b"MPC_XY_VEL_MAX", 1e9, 20.0), (b"MPC_THR_MAX", -5.0, 0.0)):
        peer.send(d.MAVLink_param_set_message(api.system_id, 1, name, value, d.MAV_PARAM_TYPE_REAL32))
        echo = peer.receive(lambda m, n=name: m.get_type() == "PARAM_VALUE" and m.param_id == n.decode())
        assert echo.param_value == pytest.approx(expected)
        assert table[name.decode()] == pytest.approx(expected)
    peer.send(d.MAVLink_param_set_message(api.system_id, 1, b"MPC_THR_MAX", 1.0, d.MAV_PARAM_TYPE_REAL32))
    peer.receive(lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == "MPC_THR_MAX")
    peer.send(d.MAVLink_param_set_message(api.system_id, 1, b"MPC_Z_P", INF, d.MAV_PARAM_TYPE_REAL32))
    echo = peer.receive(lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == "MPC_Z_P")
    assert math.isfinite(echo.param_value) and table["MPC_Z_P"] == pytest.approx(echo.param_value)
    _still_flying(harness, advance)


@pytest.mark.parametrize(("msgid", "interval"), [(30.0, INF), (INF, 1000.0), (30.0, -INF), (math.nan, 1e30)])
def test_message_interval_with_infinite_values_is_answered_without_error(vehicle, caplog, msgid,  # noqa: F811
                                                                         interval) -> None:
    _, _api, peer, _ = vehicle
    with caplog.at_level(logging.WARNING):
        peer.send(command_long(d.MAV_CMD_SET_MESSAGE_INTERVAL, msgid, interval))
        ack = peer.receive(lambda m: m.get_type() == "COMMAND_ACK" and m.command == d.MAV_CMD_SET_MESSAGE_INTERVAL)
    assert ack.result in (d.MAV_RESULT_ACCEPTED, d.MAV_RESULT_DENIED)
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]
