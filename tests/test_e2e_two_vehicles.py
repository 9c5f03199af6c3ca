"""Two vehicles in one session, each with its own ports and its own MAVSDK instance, flown
together by a Fleet: same checks as the single-vehicle flight, at the same time."""

from __future__ import annotations

import numpy as np
import pytest
from test_session import pick_mavlink_instances, ports_released

from sitl_bridge.client import Fleet
from sitl_bridge.client.demo import DEMO_ACTIONS, fly_leg
from sitl_bridge.session import SimSession


def test_two_vehicles_fly_the_demo_legs_together() -> None:
    base = pick_mavlink_instances(2)
    with SimSession("empty", autopilot="stub", speed_factor=0, instance_base=base, num_vehicles=2) as session, \
            Fleet(session.instances, clock=session) as fleet:
        assert [c.url for c in fleet.clients] == [f"udpin://127.0.0.1:{14540 + base + k}" for k in (0, 1)]
        assert all(c.autopilot_type() == "PX4" for c in fleet.clients)
        fleet.wait_healthy(timeout_s=30)
        fleet.arm()
        fleet.takeoff(2.5)
        for client in fleet.clients:
            assert client.relative_altitude_m() == pytest.approx(2.5, abs=0.3)
        fleet.start_offboard()
        assert [c.flight_mode() for c in fleet.clients] == ["OFFBOARD", "OFFBOARD"]
        for action in DEMO_ACTIONS:
            for leg in fly_leg(fleet, action):
                assert leg.error_m <= 0.25, leg.line()
        # Each vehicle flew its own legs: they are still 3 m apart (east), as spawned.
        east = [session.vehicle_state(k).position_enu_m[0] for k in (0, 1)]
        assert east[1] - east[0] == pytest.approx(3.0, abs=0.3)
        fleet.hold()
        fleet.land()
        assert not any(c.armed() for c in fleet.clients)
        assert np.all([session.vehicle_state(k).position_enu_m[2] < 0.3 for k in (0, 1)])
    assert ports_released(base) and ports_released(base + 1)
