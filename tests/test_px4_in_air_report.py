"""A refusal to fly a PX4 on into the next episode says what it rests on: truth and estimate of
the height, PX4's landed state, mode, armed flag and status, and how old each report is. The
reports come over a real UDP socket from a peer playing PX4's GCS link (no PX4 needed)."""

from __future__ import annotations

import socket
import time
from pathlib import Path

from sitl_bridge import mavlink
from sitl_bridge.autopilot.modes import OFFBOARD, custom_mode
from sitl_bridge.autopilot.px4.in_air import describe, refusal
from sitl_bridge.autopilot.px4.observer import GCS_BASE_PORT, GcsObserver, Px4Observation
from sitl_bridge.physics import Simulation
from sitl_bridge.world import load_world

d = mavlink.dialect
WORLD = load_world(Path(__file__).resolve().parents[1] / "worlds" / "empty.yaml")


def test_a_height_refusal_names_truth_estimate_state_and_report_ages(free_instance: int) -> None:
    px4 = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    px4.bind(("127.0.0.1", GCS_BASE_PORT + free_instance))
    observer = GcsObserver(free_instance, "127.0.0.1", {})
    obs = Px4Observation()
    try:
        observer.poll(obs)   # its first heartbeat tells the PX4 peer where the observer listens
        px4.settimeout(2.0)
        _, observer_address = px4.recvfrom(65536)
        codec = mavlink.new_codec(free_instance + 1, 1)
        armed = d.MAV_MODE_FLAG_SAFETY_ARMED | d.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        for message in (d.MAVLink_heartbeat_message(d.MAV_TYPE_QUADROTOR, d.MAV_AUTOPILOT_PX4, armed,
                                                    custom_mode(*OFFBOARD), d.MAV_STATE_ACTIVE, 3),
                        d.MAVLink_extended_sys_state_message(0, d.MAV_LANDED_STATE_IN_AIR),
                        d.MAVLink_local_position_ned_message(1000, 0.0, 0.0, -2.4, 0.0, 0.0, 0.0)):
            px4.sendto(message.pack(codec), observer_address)
        deadline = time.monotonic() + 2.0
        while len(obs.received_wall_s) < 3 and time.monotonic() < deadline:
            observer.poll(obs)
        assert set(obs.received_wall_s) == {"HEARTBEAT", "EXTENDED_SYS_STATE", "LOCAL_POSITION_NED"}
    finally:
        observer.close()
        px4.close()
    with Simulation(WORLD) as sim:   # the truth: resting on the ground (0.05 m), PX4 says 2.4 m up
        state = sim.state(0)
        reason = refusal(obs, state, 0.0, 0.0)
        assert reason.startswith("height 0.0")
        detail = describe(obs, state, 2.4, time.monotonic() + 0.5)
    assert "height truth 0.05 m, PX4 estimate 2.40 m" in detail
    assert "landed state IN_AIR, mode Offboard, armed, status ACTIVE" in detail
    ages = detail.split("report ages (wall s): ")[1]
    for name in ("HEARTBEAT", "EXTENDED_SYS_STATE", "LOCAL_POSITION_NED"):
        age = float(ages.split(f"{name} ")[1].split(",")[0])
        assert 0.5 <= age < 3.0
    assert "none received" in describe(Px4Observation(), state, None, 0.0)
