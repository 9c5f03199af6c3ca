"""Lockstep: the shared clock waits for every autopilot, run_for/hold, speed factor, runner.

Autopilot peers are the independent pymavlink peers of test_hil_link, driven either in the
lockstep thread (pumps) or from their own threads (like a separate PX4 process).
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest
from test_hil_link import Peer

from sitl_bridge.hil import HilLink, LinkClosed, Lockstep, SimRunner
from sitl_bridge.hil.lockstep import parse_speed_factor
from sitl_bridge.physics.simulation import Simulation
from sitl_bridge.sensors.suite import SensorSuite
from sitl_bridge.world.loader import load_world

WORLDS = Path(__file__).resolve().parents[1] / "worlds"
STEP_US = 4000


class ThreadPeer(Peer):
    """A peer answering from its own thread; answers only while `gate` is set, after
    `delay_s` (a slow autopilot)."""

    def __init__(self, port: int, delay_s: float = 0.0) -> None:
        super().__init__(port)
        self.gate = threading.Event()
        self.gate.set()
        self.delay_s = delay_s
        self.stop = threading.Event()
        self.sensor_times: list[int] = []
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        self.sock.settimeout(0.05)
        while not self.stop.is_set():
            try:
                data = self.sock.recv(1 << 16)
            except TimeoutError:
                continue
            except OSError:
                return
            if not data:
                return
            for message in self.codec.parse_buffer(data) or []:
                if message.get_type() == "HIL_SENSOR" and message.id == 0:
                    self.sensor_times.append(message.time_usec)
                    self.gate.wait()
                    if self.delay_s:
                        time.sleep(self.delay_s)
                    if self.stop.is_set():
                        return
                    self.send(self.actuators(message.time_usec))

    def close(self) -> None:
        self.stop.set()
        self.gate.set()
        self.thread.join(2.0)
        super().close()


def make_rig(first_instance: int, vehicles: int, peer_factory, **lockstep_args):
    world = load_world(WORLDS / ("empty.yaml" if vehicles == 1 else "two_drones_empty.yaml"))
    sim = Simulation(world)
    sensors = [SensorSuite(world.home, seed=i) for i in range(vehicles)]
    links = [HilLink(first_instance + i) for i in range(vehicles)]
    peers = [peer_factory(link.port, i) for i, link in enumerate(links)]
    for peer in peers:
        peer.greet()  # a peer becomes the autopilot once it speaks (PX4's first bytes)
    lockstep = Lockstep(sim, sensors, links, **lockstep_args)
    assert lockstep.accept_all(5.0)
    return sim, links, peers, lockstep


def close_rig(sim, links, peers) -> None:
    for peer in peers:
        peer.close()
    for link in links:
        link.close()
    sim.close()


@pytest.fixture
def pumped(free_instance):
    sim, links, peers, lockstep = make_rig(free_instance, 1, lambda port, i: Peer(port), speed_factor=0)
    lockstep.pumps.append(peers[0].pump)
    yield sim, links[0], peers[0], lockstep
    close_rig(sim, links, peers)


def test_run_for_is_exact_then_holds(pumped):
    sim, link, peer, lockstep = pumped
    assert lockstep.run_for(0.5) == 125
    assert sim.time_us == 500_000
    assert lockstep.held
    peer.pump()
    sent = len(peer.of_type("HIL_SENSOR"))
    assert sent == 125
    lockstep.idle(0.1)  # pumps and links serviced, time frozen
    peer.pump()
    assert sim.time_us == 500_000 and len(peer.of_type("HIL_SENSOR")) == sent
    lockstep.run_for(0.1)
    assert sim.time_us == 600_000
    with pytest.raises(ValueError, match="whole number"):
        lockstep.run_for(0.0041)


def test_idle_until_returns_once_the_condition_holds(pumped):
    sim, _, _, lockstep = pumped
    passes = []
    lockstep.pumps.append(lambda: passes.append(sim.time_us))
    # what it waits for arrives with the third pass: it returns then, not after the minute
    assert lockstep.idle(60.0, until=lambda: len(passes) >= 3) is True
    assert len(passes) == 3
    passes.clear()
    assert lockstep.idle(0.01, until=lambda: False) is False  # never: the timeout, then False
    assert len(passes) >= 1 and set(passes) == {sim.time_us}  # pumped, time frozen


def test_hold_runs_the_pumps_once_more_at_the_held_time(pumped):
    sim, _, _, lockstep = pumped
    seen = []
    lockstep.pumps.append(lambda: seen.append(sim.time_us))
    lockstep.run_for(0.02)
    # one pass per step (at the step's time), then one held (queued telemetry goes out)
    assert seen == [0, 4000, 8000, 12000, 16000, 20000] and sim.time_us == 20000


def test_run_for_stops_early_on_condition(pumped):
    sim, _, _, lockstep = pumped
    steps = lockstep.run_for(1.0, until=lambda: sim.time_us >= 40_000)
    assert steps == 10 and sim.time_us == 40_000


def test_no_advance_while_replies_are_withheld(free_instance):
    sim, links, peers, lockstep = make_rig(
        free_instance, 1, lambda port, i: ThreadPeer(port), speed_factor=0, actuator_timeout_s=30.0
    )
    peer = peers[0]
    runner = SimRunner(lockstep)
    try:
        runner.run_for(0.2)  # actuators flow from here on
        peer.gate.clear()
        runner.run_for(1.0, wait=False)
        deadline = time.monotonic() + 5
        while len(peer.sensor_times) < 51 and time.monotonic() < deadline:
            time.sleep(0.01)
        frozen = sim.time_us
        time.sleep(0.3)  # wall time passes, simulated time must not
        assert sim.time_us == frozen == 200_000
        assert len(peer.sensor_times) == 51  # the unanswered step's sensor message only
        peer.gate.set()
        runner.wait(timeout_s=10)
        assert sim.time_us == 1_200_000
        assert lockstep.stats.timeouts == 0
    finally:
        runner.close()
        close_rig(sim, links, peers)


def test_two_vehicles_share_one_clock(free_instances):
    first = free_instances(2)
    # vehicle 1's autopilot is slow: every step must wait for it
    sim, links, peers, lockstep = make_rig(
        first, 2, lambda port, i: ThreadPeer(port, delay_s=0.002 * i), speed_factor=0
    )
    try:
        lockstep.run_for(0.2)  # boot: actuators start flowing
        for peer in peers:
            peer.sensor_times.clear()
        stale_before = [link.stats.stale_actuator_msgs for link in links]
        lockstep.run_for(0.4)
        times0, times1 = peers[0].sensor_times, peers[1].sensor_times
        assert len(times0) == len(times1) == 100
        assert times0 == times1
        assert all(b - a == STEP_US for a, b in zip(times0, times0[1:], strict=False))
        assert lockstep.stats.wait_s > 0.1  # it really waited for the slow one
        # in lockstep every answer matches the step just sent: none arrives late
        assert [link.stats.stale_actuator_msgs for link in links] == stale_before
    finally:
        close_rig(sim, links, peers)


@pytest.mark.parametrize("factor, sim_seconds", [(0.5, 0.6), (1.0, 1.5), (5.0, 6.0)])
def test_speed_factor_is_honoured(free_instance, factor, sim_seconds):
    sim, links, peers, lockstep = make_rig(
        free_instance, 1, lambda port, i: Peer(port), speed_factor=factor
    )
    lockstep.pumps.append(peers[0].pump)
    try:
        lockstep.speed_factor = 0
        lockstep.run_for(0.4)
        if lockstep.real_time_factor < 2 * factor:
            pytest.skip(f"machine too loaded to pace at {factor}x (flat out: {lockstep.real_time_factor:.1f}x)")
        lockstep.speed_factor = factor
        start = time.monotonic()
        lockstep.run_for(sim_seconds)
        wall = time.monotonic() - start
        assert wall == pytest.approx(sim_seconds / factor, rel=0.10)
        assert lockstep.real_time_factor == pytest.approx(factor, rel=0.10)
    finally:
        close_rig(sim, links, peers)


def test_steps_do_not_wait_before_actuators_flow(free_instance):
    # PX4 boots only after sensor data flows and answers only once its controllers run.
    sim, links, peers, lockstep = make_rig(
        free_instance, 1, lambda port, i: Peer(port), speed_factor=0, actuator_timeout_s=0.05
    )
    try:
        lockstep.run_for(0.08)  # nobody answers, no timeout
        assert sim.time_us == 80_000 and lockstep.stats.timeouts == 0
        assert not links[0].actuators_flowing
    finally:
        close_rig(sim, links, peers)


def test_runner_resume_hold_and_error(free_instance):
    sim, links, peers, lockstep = make_rig(
        free_instance, 1, lambda port, i: ThreadPeer(port), speed_factor=0
    )
    runner = SimRunner(lockstep)
    try:
        runner.resume()
        deadline = time.monotonic() + 5
        while sim.time_us < 100_000 and time.monotonic() < deadline:
            time.sleep(0.01)
        runner.hold()
        held_at = sim.time_us
        assert held_at >= 100_000 and held_at % STEP_US == 0
        time.sleep(0.1)
        assert sim.time_us == held_at
        peers[0].close()  # the autopilot goes away (noticed while held or on the next step)
        with pytest.raises(LinkClosed):
            runner.resume()
            runner.wait(timeout_s=5)
    finally:
        runner.close()
        close_rig(sim, links, peers)


def test_speed_factor_parsing():
    assert parse_speed_factor("max") == 0.0
    assert parse_speed_factor("2.5") == 2.5
    assert parse_speed_factor(0) == 0.0
    with pytest.raises(ValueError):
        parse_speed_factor("-1")

