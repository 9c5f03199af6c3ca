"""Sensors: values, units, rates and noise statistics as PX4 expects them; geodesy; determinism."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sitl_bridge.physics import MotorCommand, Simulation
from sitl_bridge.sensors import Projection, SensorSuite
from sitl_bridge.sensors.environment import (
    isa_pressure_pa,
    magnetic_declination_inclination_deg,
    magnetic_field_ned_gauss,
    pressure_altitude_m,
)
from sitl_bridge.sensors.geodesy import EARTH_RADIUS_M
from sitl_bridge.world import GeoHome, load_world

WORLDS = Path(__file__).resolve().parents[1] / "worlds"
HOME = GeoHome()


def record(world_name: str = "empty", seconds: float = 2.0, seed: int = 0, commands=None):
    world = load_world(WORLDS / f"{world_name}.yaml")
    with Simulation(world, seed=seed) as sim:
        suites = [SensorSuite(world.home, seed=seed * 10 + i) for i in range(sim.num_vehicles)]
        frames = [[s.sample(sim.state(i), sim.time_us)] for i, s in enumerate(suites)]
        command = commands or [MotorCommand.disarmed()] * sim.num_vehicles
        for _ in range(int(seconds * 250)):
            sim.step(command)
            for i, s in enumerate(suites):
                frames[i].append(s.sample(sim.state(i), sim.time_us))
        return frames


@pytest.fixture(scope="module")
def at_rest():
    return record(seconds=4.0)[0][50:]  # after settling on the ground


def test_imu_at_rest_level_reads_minus_g_in_frd_with_gazebo_noise(at_rest):
    accel = np.array([f.accel_frd_m_s2 for f in at_rest])
    gyro = np.array([f.gyro_frd_rad_s for f in at_rest])
    assert np.allclose(accel.mean(axis=0), (0, 0, -9.8066), atol=0.02)
    assert np.allclose(gyro.mean(axis=0), 0.0, atol=0.003)
    # white noise per sample: density / sqrt(dt) (Gazebo IIM42653 defaults at 4 ms)
    assert np.allclose(accel.std(axis=0), 6.37e-3 / math.sqrt(0.004), rtol=0.1)
    assert np.allclose(gyro.std(axis=0), 8.727e-4 / math.sqrt(0.004), rtol=0.1)
    # never identical twice in a row (PX4 marks repeated values STALE)
    assert not np.any(np.all(np.diff(accel, axis=0) == 0, axis=1))


def test_rates_imu_every_step_mag_baro_gps_like_gazebo(at_rest):
    seconds = len(at_rest) / 250
    mags = sum(f.mag_frd_gauss is not None for f in at_rest)
    baros = sum(f.baro is not None for f in at_rest)
    gps = [f for f in at_rest if f.gps is not None]
    assert mags / seconds == pytest.approx(250 / 3, rel=0.05)   # 100 Hz requested -> every 3rd step
    assert baros / seconds == pytest.approx(50, rel=0.05)
    assert len(gps) / seconds == pytest.approx(5, rel=0.1)
    times = [f.time_us for f in at_rest]
    assert np.all(np.diff(times) == 4000)
    assert np.all(np.diff([f.time_us for f in gps]) == 200_000)


def test_first_frame_has_every_sensor():
    frame = record(seconds=0.0)[0][0]
    assert frame.time_us == 0
    assert frame.mag_frd_gauss is not None and frame.baro is not None and frame.gps is not None


def test_magnetometer_matches_the_wmm_at_home(at_rest):
    field = magnetic_field_ned_gauss(HOME)
    strength = math.sqrt(sum(c * c for c in field))
    assert strength == pytest.approx(0.48, abs=0.01)
    declination, inclination = magnetic_declination_inclination_deg(HOME)
    assert 1.5 < declination < 5.0 and 62.0 < inclination < 65.0
    mags = np.array([f.mag_frd_gauss for f in at_rest if f.mag_frd_gauss is not None])
    # the spawn faces north (PX4 yaw 0) and level: body FRD == NED
    assert np.allclose(mags.mean(axis=0), field, atol=0.002)
    assert np.all(mags.std(axis=0) > 1e-4)


def test_magnetometer_rotates_with_the_body():
    world = load_world(WORLDS / "empty.yaml")
    with Simulation(world) as sim:
        sim.place_vehicle(0, (0, 0, 0.06), yaw_enu_rad=0.0)  # facing east: PX4 yaw +90 deg
        frame = SensorSuite(world.home, seed=0).sample(sim.state(0), 0)
    n, e, d = magnetic_field_ned_gauss(HOME)
    # facing east, body x = east, body y (right) = south
    assert np.allclose(frame.mag_frd_gauss, (e, -n, d), atol=0.015)


def test_barometer_isa_at_home(at_rest):
    baros = [f.baro for f in at_rest if f.baro is not None]
    pressure = np.array([b.pressure_hpa for b in baros])
    assert pressure.mean() == pytest.approx(955.98, abs=0.02)   # ISA at 488 m + 0.06 m
    assert 0.005 < pressure.std() < 0.02                           # 1 Pa noise
    assert baros[0].temperature_c == pytest.approx(288.15 - 0.0065 * 488.06 - 273.15, abs=1e-3)
    assert np.mean([b.pressure_alt_m for b in baros]) == pytest.approx(488.06, abs=0.2)
    assert pressure_altitude_m(isa_pressure_pa(1234.5)) == pytest.approx(1234.5)


def test_gps_fields_in_hil_gps_units(at_rest):
    fixes = [f.gps for f in at_rest if f.gps is not None]
    g = fixes[0]
    assert (g.fix_type, g.satellites, g.eph_cm, g.epv_cm) == (3, 10, 100, 100)
    assert all(isinstance(x, int) for x in (g.lat_e7, g.lon_e7, g.alt_mm, g.vn_cm_s, g.cog_cdeg))
    lat = np.array([f.lat_e7 for f in fixes]) * 1e-7
    assert lat.mean() == pytest.approx(HOME.lat_deg, abs=1e-6)
    assert np.mean([f.alt_mm for f in fixes]) == pytest.approx(488_060, abs=30)
    assert len({f.lat_e7 for f in fixes}) > 1  # noisy
    assert all(0 <= f.cog_cdeg < 36000 for f in fixes)


def test_ground_truth_follows_a_falling_vehicle():
    world = load_world(WORLDS / "empty.yaml")
    with Simulation(world) as sim:
        suite = SensorSuite(world.home, seed=0)
        sim.place_vehicle(0, (3.0, 4.0, 20.0), yaw_enu_rad=math.pi / 2)
        for _ in range(250):
            sim.step([MotorCommand.disarmed()])
        frame = suite.sample(sim.state(0), sim.time_us)
    truth = frame.truth
    assert np.allclose(truth.position_ned_m[:2], (4.0, 3.0))
    assert truth.velocity_ned_m_s[2] == pytest.approx(9.8066, rel=1e-6)      # falling = +down
    assert truth.accel_ned_m_s2[2] == pytest.approx(9.8066, rel=1e-6)
    assert np.allclose(frame.accel_frd_m_s2, 0.0, atol=0.5)                    # free fall: ~0 + noise
    assert np.allclose(truth.quaternion_ned_frd, (1, 0, 0, 0), atol=1e-9)
    assert truth.alt_mm == round((488.0 + truth.position_ned_m[2] * -1) * 1000)
    north_deg = math.degrees(4.0 / EARTH_RADIUS_M)
    assert truth.lat_e7 == pytest.approx((HOME.lat_deg + north_deg) * 1e7, abs=1)


@settings(deadline=None)  # a busy shared machine must not fail a property
@given(st.floats(-5000, 5000), st.floats(-5000, 5000), st.floats(-100, 100))
def test_geodesy_round_trip(north, east, down):
    proj = Projection(HOME)
    lat, lon, alt = proj.to_geodetic(north, east, down)
    back = proj.to_local(lat, lon, alt)
    assert np.allclose(back, (north, east, down), atol=1e-5)


def test_geodesy_matches_gazebo_radius():
    lat, lon, alt = Projection(HOME).to_geodetic(1000.0, 0.0, -10.0)
    assert lat - HOME.lat_deg == pytest.approx(math.degrees(1000.0 / 6_353_000.0), rel=1e-6)
    assert lon == pytest.approx(HOME.lon_deg) and alt == pytest.approx(498.0)


def _stream(frames):
    out = []
    for f in frames:
        out.append((f.time_us, f.accel_frd_m_s2.tolist(), f.gyro_frd_rad_s.tolist(),
                    None if f.mag_frd_gauss is None else f.mag_frd_gauss.tolist(), f.baro, f.gps,
                    f.truth.position_ned_m.tolist()))
    return out


def test_same_seed_same_sensor_streams_different_seed_differs():
    a = record("two_drones_empty", seconds=1.0, seed=4)
    b = record("two_drones_empty", seconds=1.0, seed=4)
    c = record("two_drones_empty", seconds=1.0, seed=5)
    assert _stream(a[0]) == _stream(b[0]) and _stream(a[1]) == _stream(b[1])
    assert _stream(a[0]) != _stream(c[0])
    assert _stream(a[0])[5][1] != _stream(a[1])[5][1]  # each vehicle its own noise


def test_reset_restarts_the_noise_stream():
    world = load_world(WORLDS / "empty.yaml")
    with Simulation(world) as sim:
        suite = SensorSuite(world.home, seed=1)
        first = [suite.sample(sim.state(0), t).accel_frd_m_s2.tolist() for t in range(0, 40000, 4000)]
        suite.reset()
        again = [suite.sample(sim.state(0), t).accel_frd_m_s2.tolist() for t in range(0, 40000, 4000)]
    assert first == again


def test_sample_values_are_samples_values():
    """The HIL link's per-step `sample_values` draws and reports exactly what `sample` does."""
    world = load_world(WORLDS / "empty.yaml")
    with Simulation(world) as sim:
        framed, plain = SensorSuite(world.home, seed=3), SensorSuite(world.home, seed=3)
        hover = MotorCommand((0.7, 0.7, 0.7, 0.7), True)
        slow = [0, 0, 0]
        for _ in range(300):  # lifting off: every sensor, mag/baro/GPS at their own rates
            frame = framed.sample(sim.state(0), sim.time_us)
            values = plain.sample_values(sim.vehicle_vector(0), sim.time_us)
            mag = None if frame.mag_frd_gauss is None else tuple(frame.mag_frd_gauss.tolist())
            assert values == (*frame.accel_frd_m_s2.tolist(), *frame.gyro_frd_rad_s.tolist(), mag, frame.baro,
                              frame.gps)
            assert plain.ground_truth(sim.state(0)).raw == frame.truth.raw
            slow = [n + (v is not None) for n, v in zip(slow, values[6:], strict=True)]
            sim.step([hover])
    assert min(slow) >= 5  # mag, baro and GPS samples were compared too


def test_hand_built_state_and_truth_behave_like_generated_ones():
    from sitl_bridge.physics import VehicleState
    from sitl_bridge.sensors import GroundTruth

    state = VehicleState(position_enu_m=np.array([1.0, 2.0, 3.0]), quaternion_enu_flu=(1, 0, 0, 0),
                         velocity_enu_m_s=[0, 1, 0], angular_velocity_flu_rad_s=(0, 0, 0.5),
                         specific_force_flu_m_s2=(0, 0, 9.8066), rotor_speeds_rad_s=(800,) * 4)
    assert state.position_ned_m.tolist() == [2.0, 1.0, -3.0]
    assert state.velocity_ned_m_s.tolist() == [1.0, 0.0, 0.0]
    assert state.angular_velocity_frd_rad_s.tolist() == [0.0, 0.0, -0.5]
    assert not state.position_enu_m.flags.writeable  # immutable like a frozen dataclass
    frame = SensorSuite(HOME, seed=0).sample(state, 0)
    assert np.allclose(frame.truth.position_ned_m, (2, 1, -3))
    assert frame.truth.alt_mm == 491_000
    truth = GroundTruth((1, 0, 0, 0), (0, 0, 0), 1, 2, 3, (0, 0, 0), (0, 0, 0), (4, 5, 6))
    assert (truth.lat_e7, truth.lon_e7, truth.alt_mm) == (1, 2, 3)
    assert truth.position_ned_m.tolist() == [4, 5, 6]
