"""Offboard loss: when MAVSDK's setpoint stream stops, the autopilot leaves OFFBOARD after
COM_OF_LOSS_T of simulated time (px4_params: Hold), and not before."""

from __future__ import annotations

import pytest
from test_session import pick_mavlink_instances

from sitl_bridge.client import OffboardClient
from sitl_bridge.session import SimSession


def test_offboard_loss_triggers_the_failsafe_in_simulated_time() -> None:
    instance = pick_mavlink_instances(1)
    with SimSession("empty", autopilot="stub", speed_factor=0, instance_base=instance) as session:
        stub = session.autopilots.stubs[0]
        with OffboardClient(instance, clock=session) as client:
            client.wait_healthy(timeout_s=30)
            # At F = 0 the wall-clock timeout of px4_params (1 s) is scaled by 30 (see session).
            assert client.get_param_float("COM_OF_LOSS_T") == pytest.approx(30.0)
            client.set_param_float("COM_OF_LOSS_T", 2.0)
            client.arm()
            client.takeoff(2.5)
            client.start_offboard()
        # MAVSDK is gone: no more setpoints. Simulated time is what counts, not wall time.
        session.run_for(1.6)
        assert session.vehicle_summary(0)[0] == "Offboard"
        session.run_for(0.8)
        with OffboardClient(instance, clock=session) as observer:
            assert observer.flight_mode() == "HOLD"
            assert observer.armed() and observer.in_air()
        assert stub.armed
