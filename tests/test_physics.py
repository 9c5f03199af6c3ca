"""Iris physics on real pybullet: hover, free fall, PX4 motor conventions, collisions, clock."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from sitl_bridge.physics import IrisParams, MotorCommand, Simulation
from sitl_bridge.world import load_world

WORLDS = Path(__file__).resolve().parents[1] / "worlds"
PARAMS = IrisParams()
HOVER = PARAMS.hover_input()
STEPS_PER_S = 250


@pytest.fixture
def empty_sim():
    with Simulation(load_world(WORLDS / "empty.yaml")) as sim:
        yield sim


def fly(sim: Simulation, controls, seconds: float, armed: bool = True) -> None:
    command = [MotorCommand(tuple(controls), armed)] * sim.num_vehicles
    for _ in range(int(round(seconds * STEPS_PER_S))):
        sim.step(command)


def test_parameters_match_gazebo_iris():
    assert PARAMS.mass_kg == pytest.approx(1.55)
    assert PARAMS.rotor_directions == (1, 1, -1, -1)  # motors 1, 2 CCW; 3, 4 CW
    assert 0.6 < HOVER < 0.8


def test_integer_microsecond_clock(empty_sim):
    assert empty_sim.time_us == 0
    fly(empty_sim, (0, 0, 0, 0), 1.0, armed=False)
    assert empty_sim.time_us == 1_000_000 and isinstance(empty_sim.time_us, int)
    with Simulation(load_world(WORLDS / "empty.yaml"), step_us=1000) as fine:
        fine.step([MotorCommand.disarmed()])
        assert fine.time_us == 1000


def test_hover_input_holds_altitude(empty_sim):
    empty_sim.place_vehicle(0, (0, 0, 3.0), rotor_speeds_rad_s=empty_sim.hover_rotor_speeds_rad_s())
    heights = []
    for _ in range(2 * STEPS_PER_S):
        empty_sim.step([MotorCommand((HOVER,) * 4, True)])
        heights.append(empty_sim.state(0).position_enu_m[2])
    assert max(abs(h - 3.0) for h in heights) < 0.03
    state = empty_sim.state(0)
    assert np.allclose(state.rotor_speeds_rad_s, 1000 * HOVER + 100, rtol=1e-3)
    assert np.allclose(state.euler_ned_frd_rad[:2], 0.0, atol=1e-6)


def test_hover_from_rest_sags_only_during_spool_up(empty_sim):
    empty_sim.place_vehicle(0, (0, 0, 3.0))  # rotors at rest: the motor lag costs some height
    fly(empty_sim, (HOVER,) * 4, 0.2)
    sink_m_s = -empty_sim.state(0).velocity_enu_m_s[2]
    assert 0.0 < sink_m_s < 0.5
    fly(empty_sim, (HOVER,) * 4, 0.2)
    # only the thrust fade with axial airspeed (1 - v/25) keeps pulling, slowly
    assert -empty_sim.state(0).velocity_enu_m_s[2] == pytest.approx(sink_m_s, abs=0.03)


def test_motors_off_free_fall_at_g(empty_sim):
    empty_sim.place_vehicle(0, (0, 0, 20.0))
    fly(empty_sim, (0, 0, 0, 0), 1.0, armed=False)
    state = empty_sim.state(0)
    g = empty_sim.gravity_m_s2
    assert state.velocity_enu_m_s[2] == pytest.approx(-g, rel=1e-6)
    assert state.acceleration_enu_m_s2[2] == pytest.approx(-g, rel=1e-6)
    assert np.allclose(state.specific_force_flu_m_s2, 0.0, atol=1e-6)  # accelerometer reads 0 in free fall
    assert 20.0 - state.position_enu_m[2] == pytest.approx(0.5 * g, rel=0.01)


def test_armed_zero_input_idles_at_100_rad_s_and_disarm_spins_down(empty_sim):
    fly(empty_sim, (0, 0, 0, 0), 0.5, armed=True)
    assert np.allclose(empty_sim.state(0).rotor_speeds_rad_s, 100.0, rtol=1e-3)
    fly(empty_sim, (1, 1, 1, 1), 0.5, armed=False)
    assert np.all(empty_sim.state(0).rotor_speeds_rad_s < 1.0)


def test_motor_lag_is_faster_up_than_down(empty_sim):
    empty_sim.place_vehicle(0, (0, 0, 50.0))
    empty_sim.step([MotorCommand((1, 1, 1, 1), True)])
    up = empty_sim.state(0).rotor_speeds_rad_s[0]
    assert up == pytest.approx(1100 * (1 - math.exp(-0.004 / 0.0125)))
    fly(empty_sim, (1, 1, 1, 1), 0.5)
    empty_sim.step([MotorCommand((0, 0, 0, 0), False)])
    down = empty_sim.state(0).rotor_speeds_rad_s[0]
    assert down == pytest.approx(1100 * math.exp(-0.004 / 0.025), rel=1e-3)


def test_differential_input_yaws_the_way_px4_expects(empty_sim):
    # CCW rotors 1, 2 faster -> +yaw moment in FRD (nose turns right, PX4 yaw increases)
    empty_sim.place_vehicle(0, (0, 0, 10.0), yaw_enu_rad=math.pi / 2)  # PX4 yaw 0 (north)
    d = 0.05
    fly(empty_sim, (HOVER + d, HOVER + d, HOVER - d, HOVER - d), 0.3)
    state = empty_sim.state(0)
    assert state.angular_velocity_frd_rad_s[2] > 0.5
    assert state.euler_ned_frd_rad[2] > 0.05
    # and the other way round
    empty_sim.place_vehicle(0, (0, 0, 10.0), yaw_enu_rad=math.pi / 2)
    fly(empty_sim, (HOVER - d, HOVER - d, HOVER + d, HOVER + d), 0.3)
    assert empty_sim.state(0).angular_velocity_frd_rad_s[2] < -0.5


def test_roll_and_pitch_follow_quad_x_layout(empty_sim):
    d = 0.03
    empty_sim.place_vehicle(0, (0, 0, 10.0), yaw_enu_rad=math.pi / 2)
    # right motors (1 front-right, 4 back-right) weaker -> right side drops -> positive roll
    fly(empty_sim, (HOVER - d, HOVER + d, HOVER + d, HOVER - d), 0.2)
    assert empty_sim.state(0).angular_velocity_frd_rad_s[0] > 0.3
    empty_sim.place_vehicle(0, (0, 0, 10.0), yaw_enu_rad=math.pi / 2)
    # front motors (1, 3) stronger -> nose up -> positive pitch
    fly(empty_sim, (HOVER + d, HOVER - d, HOVER + d, HOVER - d), 0.2)
    assert empty_sim.state(0).angular_velocity_frd_rad_s[1] > 0.3
    # a tilted vehicle accelerates horizontally: nose-up pitch flies backwards (south)
    fly(empty_sim, (HOVER,) * 4, 0.5)
    assert empty_sim.state(0).velocity_ned_m_s[0] < -0.1


def test_resting_on_ground_reads_minus_g_and_no_collision(empty_sim):
    fly(empty_sim, (0, 0, 0, 0), 0.5, armed=False)
    state = empty_sim.state(0)
    assert state.on_ground
    assert state.specific_force_frd_m_s2[2] == pytest.approx(-empty_sim.gravity_m_s2, abs=0.05)
    assert empty_sim.collisions() == []


def test_hard_ground_contact_is_a_collision(empty_sim):
    empty_sim.place_vehicle(0, (0, 0, 5.0))
    hits = []
    for _ in range(2 * STEPS_PER_S):
        empty_sim.step([MotorCommand.disarmed()])
        hits += empty_sim.collisions()
    assert hits and hits[0].kind == "ground" and hits[0].speed_m_s > 5.0


def test_obstacle_collision_names_the_obstacle():
    with Simulation(load_world(WORLDS / "obstacle.yaml")) as sim:
        block = sim.world.obstacles[0]
        face_y = block.position_m[1] - block.shape.size_m[1] / 2
        sim.place_vehicle(0, (0, face_y - 0.5, 1.5), yaw_enu_rad=math.pi / 2)
        hits = []  # back motors (2, 4) stronger: nose down, fly north into the block
        for _ in range(STEPS_PER_S):
            sim.step([MotorCommand((HOVER - 0.02, HOVER + 0.02, HOVER - 0.02, HOVER + 0.02), True)])
            hits += sim.collisions()
            if hits:
                break
        assert hits, sim.state(0)
        assert (hits[0].vehicle, hits[0].kind, hits[0].other) == (0, "obstacle", "block")


def test_vehicle_vehicle_collision():
    with Simulation(load_world(WORLDS / "two_drones_empty.yaml")) as sim:
        sim.place_vehicle(0, (0, 0, 3.0))
        sim.place_vehicle(1, (0.3, 0.0, 3.0))  # boxes are 0.47 m wide: overlapping
        sim.step([MotorCommand((HOVER,) * 4, True)] * 2)
        kinds = {(c.vehicle, c.kind, c.other) for c in sim.collisions()}
        assert (0, "vehicle", "drone1") in kinds and (1, "vehicle", "drone0") in kinds


def test_wrong_number_of_commands_is_an_error(empty_sim):
    with pytest.raises(ValueError, match="expected 1 motor commands"):
        empty_sim.step([])


def test_two_simulations_in_one_process_are_independent():
    world = load_world(WORLDS / "empty.yaml")
    with Simulation(world) as a, Simulation(world) as b:
        assert a.client_id != b.client_id
        a.place_vehicle(0, (0, 0, 10.0))
        b.place_vehicle(0, (0, 0, 10.0), rotor_speeds_rad_s=b.hover_rotor_speeds_rad_s())
        for _ in range(100):
            a.step([MotorCommand.disarmed()])
            b.step([MotorCommand((HOVER,) * 4, True)])
        assert a.state(0).position_enu_m[2] < 9.5   # fell 0.78 m in 0.4 s
        assert b.state(0).position_enu_m[2] > 9.99  # hovered


def run_trace(world_name: str, seed: int, steps: int = 400) -> list[tuple]:
    with Simulation(load_world(WORLDS / f"{world_name}.yaml"), seed=seed) as sim:
        return trace(sim, steps)


def trace(sim: Simulation, steps: int) -> list[tuple]:
    out = []
    for k in range(steps):
        u = HOVER + 0.1 * math.sin(k / 20.0)
        sim.step([MotorCommand((u, u + 0.01, u, u - 0.01), k > 10)] * sim.num_vehicles)
        out.append(tuple(tuple(sim.state(i).raw) for i in range(sim.num_vehicles)))
    return out


def test_same_seed_same_trajectory_and_layout():
    assert run_trace("random_obstacle", 7) == run_trace("random_obstacle", 7)
    assert run_trace("two_drones_window", 1) == run_trace("two_drones_window", 1)
    assert run_trace("street", 2, steps=600) == run_trace("street", 2, steps=600)  # movers, contacts


def test_reset_restarts_exactly_like_a_new_simulation():
    world = load_world(WORLDS / "random_obstacle.yaml")
    with Simulation(world, seed=3) as sim, Simulation(world, seed=4) as fresh:
        first = sim.layout
        trace(sim, 200)
        sim.reset(seed=4)
        assert sim.time_us == 0
        assert sim.layout == fresh.layout != first
        assert trace(sim, 300) == trace(fresh, 300)
        sim.reset()  # no seed: next layout from the same stream, still deterministic
        assert sim.layout != fresh.layout


def collision_log(world_name: str, exhaustive: bool, steps: int = 1500) -> list:
    with Simulation(load_world(WORLDS / f"{world_name}.yaml"), seed=1) as sim:
        if exhaustive:
            sim._may_touch = lambda *args: True  # always ask pybullet for contacts
        for i in range(sim.num_vehicles):
            sim.place_vehicle(i, (0.0, sim.pose(i)[0][1], 2.0), yaw_enu_rad=0.0)
        log = []
        for k in range(steps):
            # tilt east, then cut the motors: fly into walls, each other, the ground
            u = (HOVER - 0.03, HOVER + 0.03, HOVER - 0.03, HOVER + 0.03) if k < 400 else (0, 0, 0, 0)
            sim.step([MotorCommand(u, k < 400)] * sim.num_vehicles)
            log += [(c.vehicle, c.kind, c.other, c.time_us) for c in sim.collisions()]
            log += [("ground", i, sim.state(i).on_ground) for i in range(sim.num_vehicles)]
        return log


@pytest.mark.parametrize("world_name", ["two_drones_window", "street", "two_drones_empty"])
def test_contact_prefilter_misses_nothing(world_name):
    fast = collision_log(world_name, exhaustive=False)
    assert any(entry[1] in ("obstacle", "ground", "vehicle") for entry in fast if len(entry) == 4)
    assert fast == collision_log(world_name, exhaustive=True)


@pytest.mark.parametrize("world_name", ["empty", "two_drones_window", "street"])
def test_vehicles_spawned_on_the_ground_start_at_rest(world_name):
    # no touchdown spike in the first frames (PX4's preflight checks would see it)
    with Simulation(load_world(WORLDS / f"{world_name}.yaml"), seed=1) as sim:
        for _ in range(50):
            sim.step([MotorCommand.disarmed()] * sim.num_vehicles)
            for i in range(sim.num_vehicles):
                state = sim.state(i)
                assert np.allclose(state.specific_force_frd_m_s2, (0, 0, -sim.gravity_m_s2), atol=0.05)
                assert state.on_ground and sim.collisions() == []


def test_out_of_range_and_nan_inputs_are_clamped(empty_sim):
    empty_sim.place_vehicle(0, (0, 0, 5.0))
    fly(empty_sim, (float("nan"), -3.0, 7.0, 1.0), 0.5)
    speeds = empty_sim.state(0).rotor_speeds_rad_s
    assert np.allclose(speeds, (100, 100, 1100, 1100), rtol=1e-3)
    assert np.all(np.isfinite(empty_sim.state(0).position_enu_m))



def test_a_blown_up_state_raises_instead_of_spreading_nan(empty_sim):
    from sitl_bridge.physics import PhysicsError

    empty_sim.place_vehicle(0, (0, 0, 5.0), velocity_enu_m_s=(float("nan"), 0, 0))
    with pytest.raises(PhysicsError, match="no longer finite"):
        empty_sim.step([MotorCommand.disarmed()])
    empty_sim.reset()
    empty_sim.step([MotorCommand.disarmed()])  # usable again after a reset
    assert np.all(np.isfinite(empty_sim.state(0).position_enu_m))
