"""Episode resets in the air: the sensors' measured position offset, the continuous teleport
of `Lockstep.reset_simulation(continuous=True)`, and (with PX4_BIN) real PX4 flying on from one
episode into the next with nothing leaking between them, or booting again after a crash."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from sitl_bridge.hil import HilLink, Lockstep
from sitl_bridge.physics import MotorCommand, Simulation
from sitl_bridge.sensors import Projection, SensorSuite
from sitl_bridge.sensors.suite import MAX_POSITION_OFFSET_M
from sitl_bridge.world import load_world

WORLDS = Path(__file__).resolve().parents[1] / "worlds"


def test_measured_offset_shifts_every_reported_position_and_nothing_else():
    world = load_world(WORLDS / "empty.yaml")
    with Simulation(world) as sim:
        plain, shifted = SensorSuite(world.home, seed=3), SensorSuite(world.home, seed=3)
        shifted.position_offset_ned_m = (10.0, -5.0, 1.0)
        state = sim.state(0)
        a, b = plain.sample(state, 0), shifted.sample(state, 0)
        projection = Projection(world.home)
        moved = np.subtract(projection.to_local(b.gps.lat_e7 * 1e-7, b.gps.lon_e7 * 1e-7, b.gps.alt_mm * 1e-3),
                            projection.to_local(a.gps.lat_e7 * 1e-7, a.gps.lon_e7 * 1e-7, a.gps.alt_mm * 1e-3))
        assert np.allclose(moved, (10.0, -5.0, 1.0), atol=0.02)
        assert np.allclose(b.truth.position_ned_m - a.truth.position_ned_m, (10.0, -5.0, 1.0))
        assert b.baro.pressure_alt_m - a.baro.pressure_alt_m == pytest.approx(-1.0, abs=0.01)
        assert np.array_equal(a.accel_frd_m_s2, b.accel_frd_m_s2) and b.gps.vn_cm_s == a.gps.vn_cm_s
        shifted.reset(3)
        assert shifted.position_offset_ned_m == (0.0, 0.0, 0.0)
        with pytest.raises(ValueError, match="beyond"):
            shifted.position_offset_ned_m = (MAX_POSITION_OFFSET_M[0] + 1.0, 0.0, 0.0)


def test_an_estimate_far_from_the_truth_is_not_placed():
    """The in-air reset places a vehicle in its autopilot's estimated tilt and velocity only
    when they are close to the truth (a stale report must not throw the vehicle)."""
    from sitl_bridge.autopilot.in_air_reset import Estimate, _correction_refusal

    world = load_world(WORLDS / "empty.yaml")
    with Simulation(world) as sim:
        sim.place_vehicle(0, (0.0, 0.0, 3.0), velocity_enu_m_s=(0.1, 0.0, 0.0))  # east
        state = sim.state(0)
        assert _correction_refusal(Estimate((0.0, 0.0, 0.0), (0.02, 0.12, 0.0), (0.01, -0.01)), state) == ""
        assert "tilt" in _correction_refusal(Estimate((0.0, 0.0, 0.0), (0.0, 0.1, 0.0), (0.1, 0.0)), state)
        assert "velocity" in _correction_refusal(Estimate((0.0, 0.0, 0.0), (0.5, 0.1, 0.0), (0.0, 0.0)), state)


def _hover(sim: Simulation) -> list[MotorCommand]:
    u = sim.params.hover_input(sim.gravity_m_s2)
    return [MotorCommand((u, u, u, u), True)] * sim.num_vehicles


def test_continuous_reset_hides_the_teleport_from_the_sensors(free_instance):
    world = load_world(WORLDS / "empty.yaml")
    sim = Simulation(world)
    suite = SensorSuite(world.home, seed=0)
    link = HilLink(free_instance)  # never connected: the reset does not talk to autopilots
    try:
        lockstep = Lockstep(sim, [suite], [link])
        sim.place_vehicle(0, (3.0, 4.0, 7.0), 0.3, rotor_speeds_rad_s=sim.hover_rotor_speeds_rad_s())
        for _ in range(100):
            sim.step(_hover(sim))
        before = suite.sample(sim.state(0), sim.time_us).truth.position_ned_m
        attitude = tuple(sim.state(0).quaternion_enu_flu)

        def place(sim: Simulation) -> None:
            sim.place_vehicle(0, (0.0, 0.0, 2.56), quaternion_enu_flu=attitude,
                              rotor_speeds_rad_s=sim.hover_rotor_speeds_rad_s())

        assert lockstep.reset_simulation(1, [1], place=place, continuous=True)
        assert sim.time_us == 0 and np.allclose(sim.state(0).position_enu_m, (0.0, 0.0, 2.56))
        after = suite.sample(sim.state(0), sim.time_us)
        assert np.allclose(after.truth.position_ned_m, before, atol=1e-9)  # measured: no jump
        accel = []
        for _ in range(25):  # the finite-difference accelerometer: no spike after the teleport
            sim.step(_hover(sim))
            accel.append(suite.sample(sim.state(0), sim.time_us).accel_frd_m_s2)
        assert np.allclose(np.mean(accel, axis=0), (0.0, 0.0, -9.8066), atol=0.1)
        assert np.abs(np.asarray(accel) - (0.0, 0.0, -9.8066)).max() < 0.8  # ~6 sigma of the noise

        # onto an autopilot's estimate (`reset_in_air`): the reported position moves by the shift only
        before = suite.sample(sim.state(0), sim.time_us).truth.position_ned_m
        assert lockstep.reset_simulation(1, [1], place=place, continuous=True, shifts_ned_m=[(0.1, -0.2, 0.05)])
        after = suite.sample(sim.state(0), sim.time_us).truth.position_ned_m
        assert np.allclose(after - before, (0.1, -0.2, 0.05), atol=1e-9)

        far = MAX_POSITION_OFFSET_M[0] + 50.0  # past the bound: refused, offsets back to zero
        refused = lockstep.reset_simulation(2, [2], place=lambda s: s.place_vehicle(0, (far, 0.0, 3.0)),
                                            continuous=True)
        assert not refused and suite.position_offset_ned_m == (0.0, 0.0, 0.0)
    finally:
        link.close()
        sim.close()


# -- with a real PX4 ------------------------------------------------------------------------------
def _first_second(backend) -> np.ndarray:
    """Rows every 0.1 s of the first second under 1 m/s north: position from the episode's
    start (m), velocity (m/s), roll/pitch/yaw (deg); the truth."""
    start = np.array(backend._snapshot().states[0].position_enu_m)
    rows = []
    for _ in range(10):
        state = backend.fly([np.array([1.0, 0.0, 0.0])], 0.1).states[0]
        rows.append(np.concatenate([state.position_enu_m - start, state.velocity_enu_m_s,
                                    np.degrees(state.euler_ned_frd_rad)]))
    return np.array(rows)


def _difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Largest |a - b| of position, velocity and attitude (yaw wrapped)."""
    d = np.abs(a - b)
    d[:, 8] = np.abs((a[:, 8] - b[:, 8] + 180.0) % 360.0 - 180.0)
    return np.array([d[:, 0:3].max(), d[:, 3:6].max(), d[:, 6:9].max()])


LEAK_FLOOR = np.array([0.05, 0.08, 1.5])
"""m, m/s, deg: differences below these are noise whatever two cold starts showed."""


@pytest.mark.px4
@pytest.mark.timeout(300)
def test_px4_flies_on_into_the_next_episode_with_nothing_leaking(px4_bin):
    """Consecutive episodes started in the air (no PX4 restart) fly their first second like
    two freshly restarted ones: the same traces within what two cold starts differ by."""
    from sitl_bridge.envs.backends.session import SessionBackend
    from sitl_bridge.envs.options import EnvOptions

    world = load_world(WORLDS / "empty.yaml")
    # the env claims its instance (0, or the first free one in 0..9: `autopilot.allocation`)
    options = EnvOptions.of(autopilot="px4", px4_bin=px4_bin, speed_factor=0.0)
    backend = SessionBackend(world, options, start_altitude_m=2.5)
    try:
        backend.reset(0)  # cold start: boot, arm, takeoff, offboard
        pid = backend.session.autopilots.px4.autopilots[0].pid
        traces = [_first_second(backend)]
        for wander in ((0.0, 1.0, -0.5), (-1.0, -1.0, 0.5), (1.0, 0.0, 0.0)):  # end elsewhere each time
            backend.fly([np.array(wander)], 2.0)
            snapshot = backend.reset(0)
            assert backend.last_in_air_refusal == "", backend.last_in_air_refusal
            state = snapshot.states[0]
            assert np.allclose(state.position_enu_m, (0.0, 0.0, 2.56), atol=0.1)
            assert math.hypot(*state.velocity_enu_m_s) < 0.1
            traces.append(_first_second(backend))
        assert backend.in_air_resets == 3
        assert backend.session.autopilots.px4.autopilots[0].pid == pid  # PX4 was never restarted
        offset = backend.session.lockstep.sensors[0].position_offset_ned_m
        assert math.hypot(offset[0], offset[1]) > 1.0  # PX4 flies where it measures, elsewhere
    finally:
        backend.close()
    cold = SessionBackend(world, options, start_altitude_m=2.5)
    try:
        cold.reset(0)
        reference = _difference(traces[0], _first_second(cold))  # two cold starts
    finally:
        cold.close()
    bound = np.maximum(2.0 * reference, LEAK_FLOOR)
    for before, after in zip(traces, traces[1:], strict=False):
        assert np.all(_difference(before, after) <= bound), (_difference(before, after), reference)


@pytest.mark.px4
@pytest.mark.timeout(300)
def test_px4_boots_again_after_a_crash_into_the_ground(px4_bin):
    """A vehicle flown into the ground cannot fly on: the next reset boots a new PX4, and
    that episode starts in the air at the start altitude like any other, and flies."""
    from sitl_bridge.envs.backends.session import SessionBackend
    from sitl_bridge.envs.options import EnvOptions

    world = load_world(WORLDS / "empty.yaml")
    backend = SessionBackend(world, EnvOptions.of(autopilot="px4", px4_bin=px4_bin, speed_factor=0.0),
                             start_altitude_m=2.5)
    try:
        backend.reset(0)
        pid = backend.session.autopilots.px4.autopilots[0].pid
        crashed = backend.fly([np.array([0.0, 0.0, 2.0])], 3.0).states[0]  # NED: down into the ground
        assert crashed.position_enu_m[2] < 0.3, crashed.position_enu_m
        state = backend.reset(1).states[0]
        assert backend.last_in_air_refusal, "the PX4 on the ground should not have flown on"
        assert backend.in_air_resets == 0
        assert backend.session.autopilots.px4.autopilots[0].pid != pid  # a new PX4 process
        assert np.allclose(state.position_enu_m, (0.0, 0.0, 2.56), atol=0.1)
        assert math.hypot(*state.velocity_enu_m_s) < 0.1
        flown = backend.fly([np.array([1.0, 0.0, 0.0])], 1.0).states[0]  # NED north: ENU y
        assert flown.position_enu_m[1] - state.position_enu_m[1] > 0.3
    finally:
        backend.close()
