"""The counters and the autopilot heartbeat of one simulator link (`HilLink`)."""

from __future__ import annotations

from dataclasses import dataclass

from sitl_bridge import mavlink


@dataclass
class LinkStats:
    """Counters of one link (since construction, across reconnections)."""

    connections: int = 0
    sensor_msgs: int = 0
    gps_msgs: int = 0
    state_msgs: int = 0
    actuator_msgs: int = 0
    stale_actuator_msgs: int = 0  # answers to an earlier step than the last one sent
    heartbeats: int = 0
    commands: int = 0
    other_msgs: int = 0
    garbage_bytes: int = 0
    bad_crc: int = 0
    timeouts: int = 0
    bytes_sent: int = 0
    bytes_received: int = 0


@dataclass(frozen=True)
class AutopilotHeartbeat:
    """The latest HEARTBEAT the autopilot sent on the simulator link."""

    system_id: int
    component_id: int
    autopilot: int
    base_mode: int

    @property
    def armed(self) -> bool:
        return bool(self.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
