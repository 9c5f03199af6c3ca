"""SimSession: world resolution, the clock (run_for / hold / resume), cleanup, parameters.

The external-autopilot tests plug in `hil.peer.ConstantAutopilot` over real TCP, exactly as a
hand-started autopilot would connect to `sitl-bridge run --autopilot external`.
"""

from __future__ import annotations

import socket
import threading
import time

import pytest

from sitl_bridge.autopilot.modes import mode_name as px4_mode_name
from sitl_bridge.errors import ConfigError
from sitl_bridge.hil.peer import ConstantAutopilot
from sitl_bridge.ports import api_bind_port, api_client_port, gcs_bind_port, hil_port
from sitl_bridge.session import SimSession
from sitl_bridge.world.loader import load_world
from sitl_bridge.world.lookup import default_world_path, resolve_world, with_vehicle_count


def ports_released(instance: int) -> bool:
    """Nothing of `instance` is still bound or listening. A TCP port whose closed connection
    sits in TIME_WAIT counts as released: a new listener (SO_REUSEADDR, like HilLink) binds it."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as tcp:
        tcp.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            tcp.bind(("127.0.0.1", hil_port(instance)))
        except OSError:
            return False
    for port in (api_bind_port(instance), api_client_port(instance), gcs_bind_port(instance)):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
            try:
                udp.bind(("127.0.0.1", port))
            except OSError:
                return False
    return True


def pick_mavlink_instances(count: int = 1) -> int:
    """Like conftest's `free_instances`, but below 254: MAVLink system ids (1 + instance) are
    one byte, so vehicles that speak MAVLink need instances 0..254."""
    import random

    from conftest import instance_ports_free

    rng = random.Random()
    for _ in range(500):
        first = rng.randrange(20, 254 - count)
        if all(instance_ports_free(first + k) for k in range(count)):
            return first
    raise RuntimeError("no free block of MAVLink-capable vehicle instances")


def test_default_world_resolves_from_any_directory(tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    path = default_world_path()
    assert path.name == "empty.yaml" and path.is_file()
    assert resolve_world("empty") == path
    assert resolve_world(str(path)) == path


def test_unknown_world_is_a_one_line_config_error() -> None:
    with pytest.raises(ConfigError, match="nosuchworld: cannot find world file") as info:
        resolve_world("nosuchworld")
    assert "\n" not in str(info.value)


def test_extra_vehicles_copy_the_last_spawn_side_by_side() -> None:
    world = with_vehicle_count(load_world(default_world_path()), 3)
    assert world.num_vehicles == 3
    xs = [v.spawn.position_m[0] for v in world.vehicles]
    assert xs[1] - xs[0] == pytest.approx(3.0) and xs[2] - xs[1] == pytest.approx(3.0)
    assert len({v.name for v in world.vehicles}) == 3
    assert with_vehicle_count(world, 1).num_vehicles == 1


def _connect_later(instance: int, armed: bool = False) -> tuple[ConstantAutopilot, threading.Thread]:
    """A peer that connects as soon as the session listens (like a hand-started PX4)."""
    peer = ConstantAutopilot(instance, armed=armed)

    def connect() -> None:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            try:
                peer.connect(1.0)
            except OSError:
                time.sleep(0.01)  # the session's link is not listening yet
                continue
            peer.serve()
            return

    thread = threading.Thread(target=connect, daemon=True)
    thread.start()
    return peer, thread


def _sim_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "sitl-bridge-sim"]


def test_external_autopilot_run_for_is_exact_and_hold_freezes_time(free_instance: int) -> None:
    peer, thread = _connect_later(free_instance)
    try:
        with SimSession("empty", autopilot="external", speed_factor=0, instance_base=free_instance,
                        connect_timeout_s=20) as session:
            assert session.time_us == 0 and not session.running
            session.run_for(1.0)
            assert session.time_us == 1_000_000
            session.run_for(0.004)
            assert session.time_us == 1_004_000
            with pytest.raises(ValueError):
                session.run_for(0.001)  # not a whole number of 4 ms steps
            held_at = session.time_us
            time.sleep(0.05)  # nothing may advance while held
            assert session.time_us == held_at
            session.resume()
            deadline = time.monotonic() + 10
            while session.time_us < held_at + 100_000 and time.monotonic() < deadline:
                time.sleep(0.005)
            session.hold()
            stopped_at = session.time_us
            assert stopped_at > held_at and stopped_at % 4000 == 0
            assert session.real_time_factor > 0
            assert "t=" in session.status_line() and f"[{free_instance}]" in session.status_line()
            assert peer.sensor_msgs >= stopped_at // 4000
    finally:
        thread.join(5)
        peer.close()
    assert not _sim_threads()
    assert ports_released(free_instance)


def test_session_cleans_up_after_an_exception(free_instance: int) -> None:
    peer, thread = _connect_later(free_instance)
    try:
        with pytest.raises(RuntimeError, match="boom"), \
                SimSession("empty", autopilot="external", speed_factor=0, instance_base=free_instance) as session:
            session.resume()
            raise RuntimeError("boom")
    finally:
        thread.join(5)
        peer.close()
    assert not _sim_threads()
    assert ports_released(free_instance)


def test_external_without_autopilot_times_out_cleanly(free_instance: int) -> None:
    with pytest.raises(RuntimeError, match="no autopilot connected"):
        SimSession("empty", autopilot="external", instance_base=free_instance, connect_timeout_s=0.2).start()
    assert ports_released(free_instance)


def test_bad_arguments_are_config_errors() -> None:
    with pytest.raises(ConfigError, match="autopilot"):
        SimSession("empty", autopilot="ardupilot")
    with pytest.raises(ConfigError, match="speed_factor"):
        SimSession("empty", speed_factor=-1)


@pytest.mark.parametrize(("custom_mode", "name"), [
    (50593792, "Hold"), (393216, "Offboard"), (100925440, "Land"), (33816576, "Takeoff"),
    (84148224, "Return"), (196608, "Position"), (17039360, "Ready"),
])
def test_px4_mode_names(custom_mode: int, name: str) -> None:
    assert px4_mode_name(custom_mode) == name


# -- in-place reset (episodes) -------------------------------------------------------------
def _armable_after_s(until_armed, run_for, step_s: float = 0.02, limit_s: float = 10.0) -> float:
    """Simulated seconds until `until_armed()` (an arm attempt) succeeds, trying every step_s."""
    waited = 0.0
    while not until_armed():
        run_for(step_s)
        waited += step_s
        assert waited < limit_s, "never became armable"
    return waited


def test_stub_autopilot_reset_is_a_warm_reboot_with_params_and_clock_kept() -> None:
    from sitl_bridge.autopilot.stub import CommandResult, ParamTable
    from sitl_bridge.autopilot.stub.estimator import SensorEstimator
    from sitl_bridge.autopilot.stub.harness import StubHarness

    params = ParamTable(speed_factor=0.0)
    params.set("MIS_TAKEOFF_ALT", 3.5)
    with StubHarness(load_world(default_world_path()), params=params) as harness:
        ap = harness.autopilot
        assert ap.estimator.align_s == SensorEstimator.ALIGN_S  # a new autopilot: cold boot
        cold = _armable_after_s(lambda: ap.arm() is CommandResult.ACCEPTED, harness.run_for)
        assert cold == pytest.approx(SensorEstimator.ALIGN_S, abs=0.05)
        ap.takeoff()
        harness.run_for(2.0)
        assert ap.armed and ap.home is not None
        clock_us = ap.time_us

        controllers = (ap.commander, ap.position_control, ap.attitude_control, ap.rate_control)
        ap.reset()
        assert not ap.armed and ap.home is None and ap.estimate.origin is None
        assert all(new is not old for new, old in zip(
            (ap.commander, ap.position_control, ap.attitude_control, ap.rate_control), controllers, strict=True))
        assert ap.params is params and ap.params["MIS_TAKEOFF_ALT"] == pytest.approx(3.5)
        assert ap.time_us == clock_us  # telemetry never goes back in time
        assert ap.estimator.align_s == SensorEstimator.WARM_ALIGN_S < SensorEstimator.ALIGN_S

        harness.sim.reset(1)
        harness.sensors.reset(2)
        warm = _armable_after_s(lambda: ap.arm() is CommandResult.ACCEPTED, harness.run_for)
        assert warm == pytest.approx(SensorEstimator.WARM_ALIGN_S, abs=0.05)
        harness.take_off()
        assert ap.estimate.position_valid


def test_stub_session_resets_in_place(free_instance: int) -> None:
    from sitl_bridge.autopilot.stub import CommandResult
    from sitl_bridge.autopilot.stub.estimator import SensorEstimator

    with SimSession("obstacle", autopilot="stub", speed_factor=0, instance_base=free_instance,
                    seed=1) as session:
        stub, link = session.autopilots.stubs[0], session.links[0]
        spawn = session.vehicle_state(0).position_enu_m.copy()
        with session.exclusive():
            _armable_after_s(lambda: stub.arm() is CommandResult.ACCEPTED, session.lockstep.run_for)
            assert stub.takeoff() is CommandResult.ACCEPTED
        session.run_for(3.0)
        assert session.vehicle_state(0).position_enu_m[2] > spawn[2] + 1.0
        assert session.take_collisions() == []  # a clean takeoff
        wire_us = link.last_sent_time_usec
        api_ports = session.autopilots.vehicles[0].api.ports

        session.reset(seed=1)
        assert session.time_us == 0 and not session.running and session.seed == 1
        assert session.vehicle_state(0).position_enu_m == pytest.approx(spawn, abs=1e-6)
        assert session.autopilots.stubs[0] is stub and not stub.armed and stub.home is None
        assert session.autopilots.vehicles[0].api.ports == api_ports  # MAVSDK stays connected
        session.run_for(0.2)
        assert session.time_us == 200_000
        assert link.last_sent_time_usec == wire_us + 50 * session.sim.step_us  # 1 + 49 steps later
        assert stub.time_us == link.last_sent_time_usec  # the autopilot's clock went on
        with session.exclusive():
            warm = _armable_after_s(lambda: stub.arm() is CommandResult.ACCEPTED, session.lockstep.run_for)
        assert 0.2 + warm == pytest.approx(SensorEstimator.WARM_ALIGN_S, abs=0.05)


def test_stub_session_reset_draws_the_same_episode_as_a_new_session(free_instances) -> None:
    """After a flight and a reset, nothing of the old episode is left: the next one flies
    exactly like the first episode of a session started with that seed."""
    from sitl_bridge.autopilot.stub import CommandResult

    def take_off(session: SimSession) -> None:
        stub = session.autopilots.stubs[0]
        with session.exclusive():
            _armable_after_s(lambda: stub.arm() is CommandResult.ACCEPTED, session.lockstep.run_for)
            assert stub.takeoff() is CommandResult.ACCEPTED
        session.run_for(2.0)

    first = free_instances(2)
    with SimSession("random_obstacle", autopilot="stub", speed_factor=0, instance_base=first, seed=0) as a, \
            SimSession("random_obstacle", autopilot="stub", speed_factor=0, instance_base=first + 1,
                       seed=5) as b:
        take_off(a)
        a.reset(seed=5)
        b.reset(seed=5)  # also right after start: connecting let time run
        assert a.sim.layout.goal_of(0) == b.sim.layout.goal_of(0)
        for session in (a, b):
            take_off(session)
        assert a.time_us == b.time_us
        assert a.vehicle_state(0).position_enu_m == pytest.approx(b.vehicle_state(0).position_enu_m, abs=1e-9)


def test_deliver_pending_commands_times_out_and_external_sessions_cannot_reset(free_instance: int) -> None:
    from sitl_bridge.session import SessionError

    peer, thread = _connect_later(free_instance)
    try:
        with SimSession("empty", autopilot="external", speed_factor=0, instance_base=free_instance,
                        connect_timeout_s=20) as session:
            session.deliver_pending_commands(lambda: False)  # nothing in-process: returns at once
            with pytest.raises(SessionError, match="external"):
                session.reset(seed=1)
    finally:
        thread.join(5)
        peer.close()
    instance = pick_mavlink_instances(1)
    with SimSession("empty", autopilot="stub", speed_factor=0, instance_base=instance) as session:
        started = time.monotonic()
        with pytest.raises(SessionError, match="not delivered"):
            session.deliver_pending_commands(lambda: False, timeout_s=0.1)
        assert time.monotonic() - started < 2.0


def test_stub_process_sessions_reset_by_restarting_the_stubs() -> None:
    instance = pick_mavlink_instances(1)
    with SimSession("empty", autopilot="stub-process", speed_factor=0, instance_base=instance,
                    connect_timeout_s=30) as session:
        session.run_for(0.5)
        link = session.links[0]
        wire_us = link.last_sent_time_usec
        old_pid = session.autopilots.processes[0].pid
        session.reset(seed=2)
        assert session.time_us == 0 and session.autopilots.processes[0].pid != old_pid
        assert link.connected and link.stats.connections == 2
        session.run_for(0.5)  # the new stub answers in lockstep
        assert session.time_us == 500_000 and link.last_sent_time_usec > wire_us
        assert session.lockstep.stats.timeouts == 0


def test_a_restart_takes_over_a_runner_that_fails_on_the_dead_link(monkeypatch) -> None:
    """The held runner thread polls the links; the first poll after an autopilot died raises
    (LinkClosed) and is kept for the controlling thread. A restart begun before that poll ran
    must not fail on it: here every hold lingers 0.1 s, so the poll always lands between the
    supervisor's first look and the restart taking the lockstep over."""
    import os
    import signal

    instance = pick_mavlink_instances(1)
    with SimSession("empty", autopilot="stub-process", speed_factor=0, instance_base=instance,
                    connect_timeout_s=30) as session:
        session.run_for(0.2)
        runner, process = session.runner, session.autopilots.processes[0]
        hold = runner.hold

        def lingering_hold(timeout_s: float | None = None) -> None:
            hold(timeout_s)
            time.sleep(0.1)  # widens the race: the runner thread idles (polls) meanwhile

        monkeypatch.setattr(runner, "hold", lingering_hold)
        os.kill(process.pid, signal.SIGKILL)
        session.restart_autopilots()
        assert session.autopilots.processes[0].pid != process.pid and session.links[0].connected
        session.run_for(0.2)  # the new stub answers in lockstep
        session.check()


@pytest.mark.px4
def test_px4_sessions_reset_by_restarting_px4(px4_bin: str, px4_claim, tmp_path) -> None:
    from sitl_bridge.client import OffboardClient

    instance = px4_claim.base
    with SimSession("empty", autopilot="px4", px4_bin=px4_bin, speed_factor=0, instance_base=px4_claim,
                    run_dir=tmp_path) as session:
        session.run_for(1.0)
        link, px4 = session.links[0], session.autopilots.px4.autopilots[0]
        wire_us, old_pid = link.last_sent_time_usec, px4.pid
        session.reset(seed=1)
        assert px4.pid != old_pid and px4.ready and link.stats.connections == 2
        assert 0 < session.time_us < 60_000_000  # PX4's boot, since the reset
        assert link.last_sent_time_usec > wire_us  # PX4's clock never goes back
        with OffboardClient(instance, clock=session, url=session.api_urls[0]) as client:
            client.wait_healthy(timeout_s=60)
            client.arm()
            client.wait_until(client.armed, "armed after the restart", 5.0)
    assert ports_released(instance)
