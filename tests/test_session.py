"""SimSession: world resolution, the clock (run_for / hold / resume), cleanup, parameters.

The external-autopilot tests plug in `hil.peer.ConstantAutopilot` over real TCP, exactly as a
hand-started autopilot would connect to `sitl-bridge run --autopilot external`.
"""

from __future__ import annotations

import socket
import threading
import time

import pytest

from sitl_bridge.errors import ConfigError
from sitl_bridge.hil.peer import ConstantAutopilot
from sitl_bridge.session import (
    SimSession,
    default_world_path,
    px4_mode_name,
    resolve_world,
    with_vehicle_count,
)
from sitl_bridge.world.loader import load_world


def ports_released(instance: int) -> bool:
    """Nothing of `instance` is still bound or listening. A TCP port whose closed connection
    sits in TIME_WAIT counts as released: a new listener (SO_REUSEADDR, like HilLink) binds it."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as tcp:
        tcp.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            tcp.bind(("127.0.0.1", 4560 + instance))
        except OSError:
            return False
    for port in (14580 + instance, 14540 + instance, 18570 + instance):
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
