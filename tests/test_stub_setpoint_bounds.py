"""Unbounded setpoints do not fly the stub away or into the ground: a reposition beyond reach or
outside the world's workspace is DENIED with a reason, the tilt limit narrows near the ground
so a huge velocity push does not sink the vehicle, and commanded descents still land."""

from __future__ import annotations

import math
import subprocess
import sys

import pytest
from test_stub_api import WORLD, command_long, d, vehicle  # noqa: F401 (fixture)
from test_stub_hostile_commands import _airborne, _still_flying

from sitl_bridge.autopilot.stub.fence import Fence
from sitl_bridge.autopilot.stub.harness import StubHarness
from sitl_bridge.autopilot.stub.modes import MainMode
from sitl_bridge.errors import ConfigError

NAN = math.nan


def _reposition_result(peer, api, lat: float, lon: float, alt: float) -> int:  # noqa: ANN001
    peer.send(d.MAVLink_command_long_message(api.system_id, 1, d.MAV_CMD_DO_REPOSITION, 0,
                                             -1.0, 1.0, 0.0, NAN, lat, lon, alt))
    return peer.receive(lambda m: m.get_type() == "COMMAND_ACK" and m.command == d.MAV_CMD_DO_REPOSITION).result


def _status_texts(peer, advance) -> str:  # noqa: ANN001
    """The STATUSTEXTs sent over the next simulated moment (they go out with the streams)."""
    peer.backlog = []
    advance(0.05)
    return " | ".join(m.text for m in peer.backlog + peer.drain() if m.get_type() == "STATUSTEXT")


def test_reposition_to_an_absurd_altitude_is_denied_with_a_reason(vehicle) -> None:  # noqa: F811
    harness, api, peer, advance = _airborne(vehicle)
    lat0, lon0, _ = harness.autopilot.estimate.origin
    assert _reposition_result(peer, api, lat0, lon0, 1e30) == d.MAV_RESULT_DENIED
    text = _status_texts(peer, advance)
    assert "Reposition refused" in text and "km away" in text
    held = -harness.autopilot.estimate.position_ned_m[2]
    _still_flying(harness, advance)
    assert -harness.autopilot.estimate.position_ned_m[2] == pytest.approx(held, abs=0.5)   # did not climb


def test_reposition_outside_the_workspace_is_denied_inside_accepted(vehicle) -> None:  # noqa: F811
    harness, api, peer, advance = _airborne(vehicle)
    api.fence = Fence.of_world(WORLD)   # empty.yaml: x -5..5, y -3..12, z 0..6 (ENU)
    lat0, lon0, alt0 = harness.autopilot.estimate.origin
    north_deg = math.degrees(1.0 / 6378137.0)   # one metre north
    assert _reposition_result(peer, api, lat0 + 30 * north_deg, lon0, alt0 + 3) == d.MAV_RESULT_DENIED
    assert "outside the workspace" in _status_texts(peer, advance)
    assert _reposition_result(peer, api, lat0, lon0, alt0 + 10) == d.MAV_RESULT_DENIED      # above it
    assert _reposition_result(peer, api, lat0, lon0, alt0 - 2) == d.MAV_RESULT_DENIED       # under ground
    assert _reposition_result(peer, api, lat0 + 4 * north_deg, lon0, alt0 + 3) == d.MAV_RESULT_ACCEPTED
    advance(6.0)
    assert harness.autopilot.estimate.position_ned_m[0] == pytest.approx(4.0, abs=0.5)


def test_fence_text_round_trips_and_bad_text_is_one_line() -> None:
    fence = Fence.of_world(WORLD)
    assert Fence.from_text(fence.to_text()) == fence
    for bad in ("", "1,2,3", "a,b,c,d,e,f,g,h,i", "0,0,0,5,0,0,1,1,1", "0,0,0,0,0,0,inf,1,1"):
        with pytest.raises(ConfigError, match="--fence: expected"):
            Fence.from_text(bad)
    result = subprocess.run([sys.executable, "-m", "sitl_bridge", "stub", "--fence", "1,2"],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1, result.stderr


def _hovering_in_offboard(harness: StubHarness) -> None:
    harness.take_off()
    ap = harness.autopilot
    harness.run_for(2.0)
    ap.set_velocity_setpoint_ned((0.0, 0.0, 0.0))
    assert ap.set_mode(MainMode.OFFBOARD, 0).name == "ACCEPTED"
    harness.fly_velocity((0.0, 0.0, 0.0), 1.0)


def test_a_huge_velocity_push_near_the_ground_does_not_sink_the_vehicle() -> None:
    """2.5 m hover, 6 s of a 1e9 m/s setpoint (clamped to MPC_XY_VEL_MAX), then stop: the braking
    pitch used to sink it to 0.96 m (estimate); the narrowed tilt keeps it near 1.5 m."""
    with StubHarness(WORLD, seed=3) as harness:
        _hovering_in_offboard(harness)
        ap = harness.autopilot
        lowest = math.inf
        for k in range(220):
            harness.fly_velocity((1e9 if k < 120 else 0.0, 0.0, 0.0), 0.05)
            lowest = min(lowest, -ap.estimate.position_ned_m[2], -harness.position_ned_m[2])
        assert lowest > 1.3, f"sank to {lowest:.2f} m"


@pytest.mark.parametrize("velocity", [(0.0, 0.0, 1.0), (1.0, 0.0, 1.0), (0.0, 3.0, 2.0)],
                         ids=["straight-down", "diagonal", "fast-diagonal"])
def test_a_commanded_descent_still_reaches_the_ground(velocity) -> None:
    with StubHarness(WORLD, seed=4, ground_truth_estimate=True) as harness:
        _hovering_in_offboard(harness)
        harness.fly_velocity(velocity, 4.0)
        assert -harness.position_ned_m[2] < 0.15, f"still {-harness.position_ned_m[2]:.2f} m up"
