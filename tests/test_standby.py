"""`standby=True`: session backends in worker processes, a booted standby taking over the
episodes the flying autopilots cannot start in the air. The worker plumbing runs on the stub
(real sockets, real MAVSDK); the handover needs real PX4 (`PX4_BIN`)."""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pytest

from sitl_bridge.envs.backends import BackendError, make_backend
from sitl_bridge.envs.backends.standby import KEEP_WARM_EVERY_S, KEEP_WARM_SIM_S, _Worker
from sitl_bridge.envs.options import EnvOptions
from sitl_bridge.world import load_world

WORLDS = Path(__file__).resolve().parents[1] / "worlds"


def test_standby_needs_a_kind_that_flies_on_and_no_rendering():
    with pytest.raises(ValueError, match="standby=True needs an autopilot that flies on.*px4"):
        EnvOptions.of(autopilot="stub", standby=True)
    with pytest.raises(ValueError, match="no rendering"):
        EnvOptions.of(autopilot="px4", standby=True, render_mode="rgb_array")


def test_a_worker_flies_a_session_backend_in_its_own_process_and_reports_its_errors(free_instance):
    world = load_world(WORLDS / "empty.yaml")
    worker = _Worker(world, EnvOptions.of(autopilot="stub", instance_base=free_instance), 2.5)
    try:
        snapshot = worker.call("restart", 0)
        assert snapshot.states[0].position_enu_m[2] == pytest.approx(2.5, abs=0.2)
        moved = worker.call("fly", [np.array([1.0, 0.0, 0.0])], 1.0)  # NED: north
        assert moved.states[0].position_enu_m[1] - snapshot.states[0].position_enu_m[1] > 0.3
        assert worker.call("fly_on", 1) is None  # the stub resets in place, never in the air
        with pytest.raises(BackendError, match="ValueError: expected 1 velocities"):
            worker.call("fly", [], 1.0)
        booted = worker.call("boot", 2)  # a standby: hovers a little now and then while it waits
        time.sleep(2.5 * KEEP_WARM_EVERY_S)
        later = worker.call("fly", [np.zeros(3)], 0.2)
        assert later.time_us - booted.time_us >= round((KEEP_WARM_SIM_S + 0.2) * 1e6)
    finally:
        worker.close()
    assert worker.process.poll() == 0


def test_a_worker_stops_its_autopilots_and_exits_when_its_parent_goes(free_instance):
    world = load_world(WORLDS / "empty.yaml")
    worker = _Worker(world, EnvOptions.of(autopilot="stub", instance_base=free_instance), 2.5)
    try:
        worker.call("restart", 0)
        worker.conn.close()  # what the parent's death does to the socket
        assert worker.process.wait(30) == 0
    finally:
        if worker.process.poll() is None:
            worker.process.kill()
            worker.process.wait()


@pytest.mark.px4
@pytest.mark.timeout(300)
def test_a_standby_px4_takes_over_where_the_flying_one_cannot_fly_on(px4_bin):
    world = load_world(WORLDS / "empty.yaml")
    options = EnvOptions.of(autopilot="px4", px4_bin=px4_bin, speed_factor=0.0, standby=True)
    backend = make_backend(world, options, start_altitude_m=2.5)
    try:
        backend.reset(0)
        for episode in (1, 2):  # the second handover is to the PX4 the first one set aside
            backend.fly([np.array([0.0, 0.0, 2.0])], 3.0)  # NED: down into the ground
            snapshot = backend.reset(episode)
            assert backend.last_in_air_refusal, "the landed PX4 should not have flown on"
            assert (backend.handovers, backend.restarts) == (episode, 1), backend.last_standby_refusal
            state = snapshot.states[0]
            assert np.allclose(state.position_enu_m, (0.0, 0.0, 2.56), atol=0.1)
            assert math.hypot(*state.velocity_enu_m_s) < 0.1
            flown = backend.fly([np.array([1.0, 0.0, 0.0])], 1.0).states[0]
            assert flown.position_enu_m[1] - state.position_enu_m[1] > 0.3  # it flies the episode
        assert backend.in_air_resets == 2
        dead = backend._active
        dead.process.kill()  # the flying worker dies: the standby takes over, a new worker boots
        dead.process.wait()
        state = backend.reset(3).states[0]
        assert backend.handovers == 3 and np.allclose(state.position_enu_m, (0.0, 0.0, 2.56), atol=0.1)
        assert backend.fly([np.array([1.0, 0.0, 0.0])], 1.0).states[0].position_enu_m[1] - state.position_enu_m[1] > 0.3
        assert backend._standby is not dead and backend._standby.alive
    finally:
        backend.close()
    for worker in (backend._active, backend._standby):
        assert worker is not None and worker.process.poll() == 0
