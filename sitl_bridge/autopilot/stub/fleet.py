"""The stub as a session's autopilots: in-process (`stub`) or one process per vehicle
(`stub-process`). See `sitl_bridge.autopilot.fleet` for the contract."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING

from sitl_bridge.autopilot.fleet import (
    AutopilotFault,
    AutopilotFleet,
    FleetConfig,
    Pump,
    ServeUntil,
    SessionError,
    VehicleSummary,
    link_summary,
)
from sitl_bridge.autopilot.modes import mode_name

from .autopilot import StubAutopilot
from .fence import Fence
from .in_air_start import place_hovering
from .params import MAV_PARAM_TYPE_INT32, MAV_PARAM_TYPE_REAL32, ParamTable
from .vec import wrap_pi
from .vehicle import StubVehicle

if TYPE_CHECKING:
    from sitl_bridge.hil import HilLink, Lockstep

SETPOINT_MATCH = 1e-4
"""A stub holds the setpoint sent when each component is this close (m/s)."""
YAW_MATCH_RAD = 1e-5
"""... and the heading sent this close (MAVLink carries it as float32 radians)."""

TELEMETRY_BATCH_WALL_S = 0.002
"""In-process stubs send their telemetry streams at most this often in wall time while the
lockstep runs (`MavlinkApi` batch_wall_s; the lockstep's `hold()` pumps them out): far fewer
wake-ups of MAVSDK's thread per simulated second at speed factor 0, still one datagram per
step or two at real time."""


def stub_params(speed_factor: float, extra: Mapping[str, float]) -> ParamTable:
    """px4_params/ with the `wall` timeouts scaled to `speed_factor`, then `extra` (added
    when new; integers stay INT32)."""
    table = ParamTable(speed_factor=speed_factor)
    for name, value in extra.items():
        if name in table:
            table.set(name, value)
        else:
            kind = MAV_PARAM_TYPE_INT32 if float(value).is_integer() else MAV_PARAM_TYPE_REAL32
            table.add(name, value, kind)
    return table


class InProcessStubFleet(AutopilotFleet):
    """`stub`: one `StubVehicle` per vehicle in this process, pumped by the lockstep in the
    runner thread (no context switch: the fastest protocol path). Resets reboot each stub in
    place (`StubVehicle.reset`): the HIL connection and the API sockets stay up."""

    supports_ground_truth = True
    places_in_air = True

    def __init__(self, config: FleetConfig) -> None:
        super().__init__(config)
        self.vehicles: list[StubVehicle] = []

    @property
    def stubs(self) -> list[StubAutopilot]:
        """Each vehicle's `StubAutopilot` (the brain behind its MAVLink API)."""
        return [vehicle.autopilot for vehicle in self.vehicles]

    def start(self, links: Sequence[HilLink]) -> list[Pump]:
        config = self.config
        for instance in self.instances:
            vehicle = StubVehicle(instance, config.host, ground_truth_estimate=config.ground_truth_estimate,
                                  params=stub_params(config.speed_factor, config.params),
                                  telemetry_batch_wall_s=TELEMETRY_BATCH_WALL_S,
                                  api_streams="client" if config.api_telemetry == "client" else "onboard",
                                  fence=Fence.of_world(config.world))
            self.vehicles.append(vehicle)
            if not vehicle.connect(config.connect_timeout_s or 10.0):
                raise SessionError(f"vehicle {instance}: stub could not connect to the HIL link")
        return [vehicle.pump for vehicle in self.vehicles]

    def close(self) -> None:
        for vehicle in self.vehicles:
            vehicle.close()
        self.vehicles = []

    def reset(self, lockstep: Lockstep, reset_simulation: Callable[[], None]) -> None:
        reset_simulation()
        for vehicle in self.vehicles:
            vehicle.reset()

    def place_in_air(self, lockstep: Lockstep, altitude_m: float) -> None:
        stubs = self.stubs
        place_hovering(lockstep.sim, lockstep.sensors, stubs, altitude_m, [stub.time_us for stub in stubs])

    def restart(self, lockstep: Lockstep, reset_simulation: Callable[[], None] | None = None) -> None:
        # A cold boot: new stubs on the same ports (the old sockets are closed first).
        _shut_down_for_restart(self, lockstep, reset_simulation)
        pumps = self.start(lockstep.links)
        lockstep.pumps[:] = pumps
        self.connect(lockstep.links, pumps)

    def deliver_setpoints(self, velocities_ned_m_s: Mapping[int, Sequence[float]],
                          serve_until: ServeUntil, timeout_s: float) -> None:
        stubs = self.stubs
        targets = [(stubs[self.instances.index(instance)], tuple(float(x) for x in velocity))
                   for instance, velocity in velocities_ned_m_s.items()]

        def arrived(stub: StubAutopilot, target: tuple[float, ...]) -> bool:
            # (north, east, down) or (north, east, down, yaw rad): a heading setpoint counts too
            setpoint = stub.offboard_setpoint
            if any(abs(a - b) > SETPOINT_MATCH for a, b in zip(setpoint.velocity_ned_m_s, target[:3], strict=True)):
                return False
            return len(target) < 4 or abs(wrap_pi(setpoint.yaw_rad - target[3])) <= YAW_MATCH_RAD

        def delivered() -> bool:
            return all(arrived(stub, target) for stub, target in targets)

        serve_until(delivered, timeout_s)

    def summary(self, vehicle: int, link: HilLink) -> VehicleSummary:
        stub = self.vehicles[vehicle].autopilot
        return VehicleSummary(mode_name(stub.custom_mode), bool(stub.armed))


class StubProcessFleet(AutopilotFleet):
    """`stub-process`: each vehicle's stub is a `sitl-bridge stub -i N --once` process (in its
    own session, stopped in order on close). Resets restart the processes (cold boot)."""

    supports_ground_truth = True

    def __init__(self, config: FleetConfig) -> None:
        super().__init__(config)
        self.processes: list[subprocess.Popen[bytes]] = []

    def start(self, links: Sequence[HilLink]) -> list[Pump]:
        config = self.config
        for instance in self.instances:
            # --once: a stub whose simulator vanished (we were killed) exits instead of waiting.
            command = [sys.executable, "-m", "sitl_bridge", "stub", "-i", str(instance), "--once",
                       "--host", config.host, "--speed-factor", repr(config.speed_factor),
                       "--fence", Fence.of_world(config.world).to_text()]
            if config.ground_truth_estimate:
                command.append("--ground-truth")
            for name, value in config.params.items():
                command += ["--param", f"{name}={value!r}"]
            # Own session: a terminal's Ctrl-C reaches us only; we stop the stubs in order.
            self.processes.append(subprocess.Popen(command, stdin=subprocess.DEVNULL, start_new_session=True))
        return []

    def check(self) -> list[AutopilotFault]:
        faults = []
        for vehicle, (instance, process) in enumerate(zip(self.instances, self.processes, strict=False)):
            code = process.poll()
            if code is not None:
                faults.append(AutopilotFault(f"vehicle {instance}: stub process exited with code {code}",
                                             vehicle=vehicle, instance=instance, reason="dead"))
        return faults

    def close(self) -> None:
        for process in self.processes:
            if process.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(process.pid, signal.SIGTERM)
        for process in self.processes:
            try:
                process.wait(5.0)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(process.pid, signal.SIGKILL)
                process.wait(5.0)
        self.processes = []

    def restart(self, lockstep: Lockstep, reset_simulation: Callable[[], None] | None = None) -> None:
        _shut_down_for_restart(self, lockstep, reset_simulation)
        self.start(lockstep.links)
        self.connect(lockstep.links)

    def summary(self, vehicle: int, link: HilLink) -> VehicleSummary:
        return link_summary(link)


__all__ = ["InProcessStubFleet", "StubProcessFleet", "stub_params"]


def _shut_down_for_restart(fleet: AutopilotFleet, lockstep: Lockstep,
                           reset_simulation: Callable[[], None] | None) -> None:
    """First half of a restart: stop the autopilots, drop their links, reset the simulation."""
    fleet.close()
    for link in lockstep.links:
        link.disconnect()
    if reset_simulation is not None:
        reset_simulation()
