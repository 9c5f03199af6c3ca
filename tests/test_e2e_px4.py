"""The same flight against a real PX4 SITL (v1.16 `px4_sitl_default`): PX4 connects to our
simulator like to Gazebo, and the unchanged OffboardClient flies it through MAVSDK.
Skipped without PX4_BIN (the `px4_bin` fixture)."""

from __future__ import annotations

import random
from pathlib import Path

import pytest
from test_run_command import wait_until_serving
from test_session import ports_released

from sitl_bridge.client import Fleet, OffboardClient
from sitl_bridge.client.demo import DEMO_ACTIONS, fly_leg
from sitl_bridge.session import SimSession

pytestmark = pytest.mark.px4


def _free_px4_instance() -> int:
    """A PX4 instance in 0..9 (PX4 sends its API link to 14540+i only for i <= 9:
    px4-rc.mavlink) free now, for a child `sitl-bridge run`, which claims it itself (a claim
    cannot be handed on); the tests in this process hold theirs (`px4_claim`)."""
    from sitl_bridge.autopilot.allocation import InstancesBusy, claim_free_instances
    from sitl_bridge.ports import PX4_LAST_OWN_API_INSTANCE

    try:
        # from a random start: another run picking at the same moment likely takes another one
        first = random.randint(0, PX4_LAST_OWN_API_INSTANCE)
        with claim_free_instances(1, first=first, last=PX4_LAST_OWN_API_INSTANCE) as claim:
            return claim.base
    except InstancesBusy as exc:
        pytest.skip(str(exc))


@pytest.mark.parametrize("speed_factor", [1.0, 10.0])
def test_px4_flies_the_offboard_demo(px4_bin: str, px4_claim, tmp_path, speed_factor: float) -> None:
    """Real time (what a user watching the demo runs) and ten times faster (what training
    runs): MAVSDK streams setpoints and heartbeats in wall time, PX4 measures in simulated time."""
    instance = px4_claim.base
    with SimSession("empty", autopilot="px4", px4_bin=px4_bin, speed_factor=speed_factor, instance_base=px4_claim,
                    run_dir=tmp_path) as session:
        with Fleet.for_session(session) as fleet:
            client = fleet[0]
            assert client.autopilot_type() == "PX4"
            client.wait_healthy(timeout_s=60)
            assert all(client.health().values()), client.health()
            assert client.get_param_float("MIS_TAKEOFF_ALT") == pytest.approx(2.5)
            # px4_params: 1 s of wall time, so F s of PX4 time (PX4 measures PX4 time).
            assert client.get_param_float("COM_OF_LOSS_T") == pytest.approx(speed_factor)
            client.set_param_float("COM_OF_LOSS_T", 2.0)
            assert client.get_param_float("COM_OF_LOSS_T") == pytest.approx(2.0)
            client.arm()
            assert client.takeoff(2.5) == pytest.approx(2.5, abs=0.3)
            assert client.flight_mode() == "HOLD"
            client.start_offboard()
            # at F = 1 each simulated second is a wall second: two legs there, all six at F = 10
            for action in DEMO_ACTIONS if speed_factor > 1.0 else DEMO_ACTIONS[:2]:
                (leg,) = fly_leg(fleet, action)
                assert leg.error_m <= 0.25, leg.line()
                assert client.flight_mode() == "OFFBOARD"
        # The client is gone, its setpoint stream too: PX4's offboard-loss failsafe (Hold).
        session.run_for(3.0)
        with OffboardClient(instance, clock=session, url=session.api_urls[0]) as observer:
            # a new client knows the landed state only from PX4's next EXTENDED_SYS_STATE
            # (until then in_air() reads False): wait for it, as for the mode
            observer.wait_until(lambda: observer.flight_mode() == "HOLD" and observer.landed_state() != "UNKNOWN",
                                "failsafe Hold and a landed state", 5.0)
            assert observer.armed() and observer.in_air()
            observer.land()
            assert not observer.armed()
    assert ports_released(instance)


def _px4_pids(px4_bin: str, instance: int) -> list[int]:
    """Live PX4 processes started from `px4_bin` for `instance`."""
    import os
    from pathlib import Path

    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            argv = (entry / "cmdline").read_bytes().split(b"\0")
            state = (entry / "stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if state != "Z" and argv[:3] == [os.fsencode(px4_bin), b"-i", str(instance).encode()]:
            pids.append(int(entry.name))
    return pids


def test_ctrl_c_stops_px4_and_frees_its_ports(px4_bin: str) -> None:
    import signal
    import subprocess
    import sys

    instance = _free_px4_instance()
    process = subprocess.Popen(
        [sys.executable, "-m", "sitl_bridge", "run", "--autopilot", "px4", "--px4-bin", px4_bin,
         "--speed-factor", "1", "--instance-base", str(instance)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    output = []
    try:
        output = wait_until_serving(process, 120)
        assert _px4_pids(px4_bin, instance), "".join(output)
        process.send_signal(signal.SIGINT)
        rest, _ = process.communicate(timeout=60)
        output.append(rest)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert process.returncode == 130, "".join(output)
    assert _px4_pids(px4_bin, instance) == []
    assert ports_released(instance)


def _udp_binds(pid: int) -> list[tuple[str, int]]:
    """(address, port) of every UDP socket process `pid` has bound (`ss -lunp`)."""
    import re
    import subprocess

    out = subprocess.run(["ss", "-lunpH"], capture_output=True, text=True, check=True).stdout
    binds = []
    for line in out.splitlines():
        if f"pid={pid}," in line:
            local = line.split()[3]
            address, port = local.rsplit(":", 1)
            binds.append((re.sub(r"%.*$", "", address), int(port)))
    return binds


def test_px4_exposes_only_its_two_documented_links(px4_bin: str, px4_claim, tmp_path) -> None:
    """PX4's MAVLink module binds UDP links to 0.0.0.0 (hard-coded); our
    px4-rc.mavlink starts only the GCS (18570+i) and API (14580+i) links. Nothing else of
    PX4's listens beyond loopback (docs/autopilots.md, "Network exposure")."""
    import shutil

    if shutil.which("ss") is None:
        pytest.skip("ss (iproute2) not installed")
    from sitl_bridge.ports import vehicle_ports

    instance = px4_claim.base
    with SimSession("empty", autopilot="px4", px4_bin=px4_bin, speed_factor=0, instance_base=px4_claim,
                    run_dir=tmp_path / "run") as session:
        session.run_for(1.0)
        pid = session.autopilots.px4.autopilots[0].pid
        binds = _udp_binds(pid)
    exposed = sorted(port for address, port in binds if address not in ("127.0.0.1", "[::1]"))
    ports = vehicle_ports(instance, px4=True)
    assert exposed == sorted([ports.api_bind, ports.gcs_bind]), binds


def test_two_drones_on_px4_through_pettingzoo(px4_bin: str) -> None:
    """TE (two_drones_empty) with one PX4 process per drone, one lockstep
    clock; both act, both episodes start from the same state after a reset."""
    import numpy as np

    from sitl_bridge.envs import make_parallel_env

    env = make_parallel_env(str(Path(__file__).resolve().parents[1] / "worlds" / "two_drones_empty.yaml"), autopilot="px4", px4_bin=px4_bin, speed_factor=0, seed=0)
    try:
        observations, _ = env.reset(seed=3)
        assert len(observations) == 2
        session = env.backend.session if hasattr(env, "backend") else None
        for _ in range(3):
            observations, _, terminated, truncated, infos = env.step({agent: 0 for agent in env.agents})
            if not env.agents:
                break
        assert all(np.all(np.isfinite(o)) for o in observations.values())
        if session is not None:
            pids = [a.pid for a in session.autopilots.px4.autopilots]
            assert len(set(pids)) == 2  # one PX4 process per drone
    finally:
        env.close()
