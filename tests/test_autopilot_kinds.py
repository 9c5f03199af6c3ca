"""Autopilot kinds: the registry is the one list, a new kind is one class plus one entry (a toy
kind defined here runs a SimSession and an env episode without touching the package), faults
are what a supervisor acts on, and the status line shows what the autopilot reports."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path

import pytest

from sitl_bridge.autopilot import registry
from sitl_bridge.autopilot.fleet import (
    AutopilotFault,
    AutopilotFleet,
    FleetConfig,
    ServeUntil,
    SessionError,
    VehicleSummary,
)
from sitl_bridge.autopilot.modes import mode_name
from sitl_bridge.autopilot.stub import StubVehicle
from sitl_bridge.autopilot.stub.fleet import stub_params
from sitl_bridge.errors import ConfigError
from sitl_bridge.session import SimSession

WORLDS = Path(__file__).resolve().parents[1] / "worlds"
PACKAGE = Path(__file__).resolve().parents[1] / "sitl_bridge"


class GroundTruthStubs(AutopilotFleet):
    """A toy kind: in-process stubs that fly on ground truth and serve no GCS link, counting
    their resets. Everything it does is through the `AutopilotFleet` contract."""

    supports_ground_truth = True

    def __init__(self, config: FleetConfig) -> None:
        super().__init__(config)
        self.vehicles: list[StubVehicle] = []
        self.resets = 0

    def start(self, links: Sequence[object]) -> list[Callable[[], object]]:
        for instance in self.instances:
            vehicle = StubVehicle(instance, self.config.host, ground_truth_estimate=True, gcs=False,
                                  params=stub_params(self.config.speed_factor, self.config.params))
            self.vehicles.append(vehicle)
            assert vehicle.connect(10.0)
        return [vehicle.pump for vehicle in self.vehicles]

    def close(self) -> None:
        for vehicle in self.vehicles:
            vehicle.close()
        self.vehicles = []

    def reset(self, lockstep: object, reset_simulation: Callable[[], None]) -> None:
        reset_simulation()
        for vehicle in self.vehicles:
            vehicle.reset()
        self.resets += 1

    def restart(self, lockstep: object, reset_simulation: Callable[[], None] | None = None) -> None:
        raise SessionError("the toy cannot restart")

    def deliver_setpoints(self, velocities_ned_m_s: Mapping[int, Sequence[float]],
                          serve_until: ServeUntil, timeout_s: float) -> None:
        wanted = {self.instances.index(i): tuple(v) for i, v in velocities_ned_m_s.items()}

        def arrived() -> bool:
            return all(max(abs(a - b) for a, b in zip(self.vehicles[k].autopilot.offboard_setpoint.velocity_ned_m_s,
                                                       v, strict=True)) < 1e-4 for k, v in wanted.items())

        serve_until(arrived, timeout_s)

    def summary(self, vehicle: int, link: object) -> VehicleSummary:
        stub = self.vehicles[vehicle].autopilot
        return VehicleSummary(f"toy-{mode_name(stub.custom_mode)}", stub.armed)


@pytest.fixture
def toy_kind() -> Iterator[str]:
    registry.register(registry.AutopilotKind("toy", "in-process ground-truth stubs (a test)", fleet=GroundTruthStubs))
    try:
        yield "toy"
    finally:
        registry.unregister("toy")


def test_one_registry_names_every_kind_and_nothing_else_branches_on_it() -> None:
    assert registry.names() == ("direct", "stub", "px4", "stub-process", "external")
    assert registry.names(session=True) == ("stub", "px4", "stub-process", "external")
    assert registry.names(env=True) == ("direct", "stub", "px4")
    found = subprocess.run(["grep", "-rn", "autopilot ==", str(PACKAGE)], capture_output=True, text=True).stdout
    assert found == ""
    with pytest.raises(ConfigError, match="autopilot: expected one of stub, px4, stub-process, external"):
        SimSession("empty", autopilot="direct")
    from sitl_bridge.cli import build_parser

    parser = build_parser()
    for command in (["run"], ["train", "w.yaml"], ["eval", "r", "--world", "w.yaml"]):
        with pytest.raises(SystemExit):
            parser.parse_args([*command, "--autopilot", "nosuchkind"])


def test_a_toy_kind_runs_a_session_and_an_env_episode(toy_kind: str, free_instances) -> None:
    import sitl_bridge.envs as envs

    first = free_instances(2)
    with SimSession("empty", autopilot=toy_kind, speed_factor=0, instance_base=first) as session:
        assert isinstance(session.autopilots, GroundTruthStubs)
        session.run_for(0.5)
        assert session.time_us == 500_000
        assert f"[{first}] toy-Hold disarmed" in session.status_line()
        assert session.api_urls == [f"udpin://127.0.0.1:{14540 + first}"]
        session.reset(seed=3)
        assert session.time_us == 0 and session.autopilots.resets == 1
        assert session.faults() == []

    assert toy_kind in envs.AUTOPILOTS
    env = envs.make_env(WORLDS / "empty.yaml", autopilot=toy_kind, speed_factor=0.0, instance_base=first + 1,
                        estimator="ground_truth")
    try:
        _, info = env.reset(seed=1)
        start = info["position_enu_m"]
        for _ in range(2):
            _, _, terminated, truncated, info = env.step(3)  # north
        assert info["position_enu_m"][1] > start[1] + 1.0
        fleet = env.backend.session.autopilots
        assert isinstance(fleet, GroundTruthStubs) and fleet.resets == 1
        assert all(v.autopilot.ground_truth_estimate for v in fleet.vehicles)
        assert env.backend.session.vehicle_summary(0) == ("toy-Offboard", True)
    finally:
        env.close()


def test_a_dead_stub_process_is_a_fault_a_supervisor_can_restart(free_instance: int) -> None:
    with SimSession("empty", autopilot="stub-process", speed_factor=0, instance_base=free_instance,
                    connect_timeout_s=30) as session:
        session.run_for(0.2)
        assert session.faults() == []
        session.autopilots.processes[0].kill()
        session.autopilots.processes[0].wait(5)
        faults = session.faults()
        assert [(f.vehicle, f.instance, f.reason) for f in faults] == [(0, free_instance, "dead")]
        with pytest.raises(AutopilotFault, match="stub process exited"):
            session.check()
        session.restart_autopilots()
        assert session.faults() == []
        session.run_for(0.2)  # the new stub answers in lockstep
        assert session.time_us == 400_000


def test_a_frozen_autopilot_is_reported_as_frozen(free_instance: int) -> None:
    """A stub process that stops answering (SIGSTOP) stops the lockstep: `faults()` names it."""
    import signal

    with SimSession("empty", autopilot="stub-process", speed_factor=0, instance_base=free_instance,
                    connect_timeout_s=30, actuator_timeout_s=0.5) as session:
        session.run_for(0.2)
        process = session.autopilots.processes[0]
        os.kill(process.pid, signal.SIGSTOP)
        try:
            with pytest.raises(AutopilotFault, match="did not answer") as info:
                session.run_for(0.2)
        finally:
            os.kill(process.pid, signal.SIGCONT)
        fault = info.value
        assert (fault.vehicle, fault.instance, fault.reason) == (0, free_instance, "frozen")
        session.restart_autopilots()  # what a watchdog does
        session.run_for(0.2)
        assert session.faults() == []


# -- px4: the status line shows what PX4 reports ---------------------------------------------
FAKE_PX4 = """#!/bin/sh
# Stands in for PX4 SITL's bin/px4 (`px4 -i N -d ROOTFS`): the stub speaks the same MAVLink on
# the same ports (HIL TCP 4560+N, API 14580+N, GCS 18570+N), so the px4 kind runs unchanged.
exec {python} -m sitl_bridge stub -i "$2" --once --speed-factor "${{PX4_SIM_SPEED_FACTOR:-0}}"
"""


@pytest.fixture
def fake_px4(tmp_path: Path) -> Path:
    binary = tmp_path / "build" / "bin" / "px4"
    binary.parent.mkdir(parents=True)
    binary.write_text(FAKE_PX4.format(python=sys.executable))
    binary.chmod(binary.stat().st_mode | stat.S_IXUSR)
    rcs = tmp_path / "build" / "etc" / "init.d-posix" / "rcS"
    rcs.parent.mkdir(parents=True)
    rcs.write_text("# not used by the stand-in\n")
    return binary


def test_px4_status_line_shows_the_mode_and_armed_flag_px4_reports(fake_px4: Path, px4_claim, tmp_path: Path) -> None:
    """The bug: with --autopilot px4 the status line said `Hold disarmed` for a whole flight.
    The px4 kind reads PX4's HEARTBEAT on its GCS link when asked; here a MAVLink peer that
    speaks PX4's protocol (the stub behind a stand-in bin/px4) flies offboard."""
    from sitl_bridge.client import OffboardClient

    instance = px4_claim.base
    with SimSession("empty", autopilot="px4", px4_bin=fake_px4, speed_factor=0, instance_base=px4_claim,
                    run_dir=tmp_path / "run") as session:
        assert session.vehicle_summary(0) == ("Hold", False)
        with OffboardClient(instance, clock=session, url=session.api_urls[0]) as client:
            client.wait_healthy(timeout_s=30)
            client.arm()
            client.takeoff(2.5)
            client.start_offboard()
            session.run_for(1.0)
            assert session.vehicle_summary(0) == ("Offboard", True)
            assert f"[{instance}] Offboard ARMED" in session.status_line()


def test_in_process_stubs_restart_cold_on_the_same_ports(free_instance: int) -> None:
    with SimSession("empty", autopilot="stub", speed_factor=0, instance_base=free_instance) as session:
        session.run_for(0.5)
        old = session.autopilots.stubs[0]
        ports = session.autopilots.vehicles[0].api.ports
        session.restart_autopilots()
        session.run_for(0.5)
        assert session.autopilots.stubs[0] is not old and session.autopilots.vehicles[0].api.ports == ports
        assert session.faults() == [] and session.lockstep.stats.timeouts == 0
        assert session.links[0].stats.connections == 2
