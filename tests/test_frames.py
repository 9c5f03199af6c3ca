"""Frame conventions: property-based round trips and known orientations."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from sitl_bridge import frames

finite = st.floats(min_value=-1e3, max_value=1e3, allow_nan=False, allow_infinity=False)
vectors = st.tuples(finite, finite, finite)
angles = st.floats(min_value=-math.pi, max_value=math.pi, allow_nan=False)
quaternions = st.tuples(*[st.floats(min_value=-1, max_value=1, allow_nan=False)] * 4).filter(
    lambda q: sum(c * c for c in q) > 1e-3).map(lambda q: frames.quat_normalize(q))


def same_rotation(a, b, tol=1e-9) -> bool:
    return abs(abs(float(np.dot(a, b))) - 1.0) < tol


@settings(deadline=None)  # a busy shared machine must not fail a property
@given(vectors)
def test_world_and_body_vector_conversions_round_trip(v):
    assert np.allclose(frames.ned_to_enu(frames.enu_to_ned(v)), v)
    assert np.allclose(frames.frd_to_flu(frames.flu_to_frd(v)), v)
    assert frames.ned_to_enu_xyz(*frames.enu_to_ned_xyz(*v)) == tuple(v)
    assert frames.frd_to_flu_xyz(*frames.flu_to_frd_xyz(*v)) == tuple(v)


def test_axis_mapping():
    east, north, up = (1, 0, 0), (0, 1, 0), (0, 0, 1)
    assert frames.enu_to_ned(east).tolist() == [0, 1, 0]
    assert frames.enu_to_ned(north).tolist() == [1, 0, 0]
    assert frames.enu_to_ned(up).tolist() == [0, 0, -1]
    assert frames.flu_to_frd((0, 1, 0)).tolist() == [0, -1, 0]  # left -> -right
    assert np.allclose(frames.enu_to_ned(np.ones((5, 3)) * (1, 2, 3)), [[2, 1, -3]] * 5)


@settings(deadline=None)  # a busy shared machine must not fail a property
@given(quaternions)
def test_attitude_conversion_round_trips_and_matches_the_generic_product(q):
    q_ned_frd = frames.quat_enu_flu_to_ned_frd(q)
    generic = frames.quat_multiply(frames.quat_multiply(frames.Q_NED_ENU, q), frames.quat_conjugate(frames.Q_FRD_FLU))
    assert np.allclose(q_ned_frd, generic)
    assert same_rotation(frames.quat_ned_frd_to_enu_flu(q_ned_frd), q)


@settings(deadline=None)  # a busy shared machine must not fail a property
@given(quaternions, vectors)
def test_attitude_conversion_is_consistent_with_vector_conversions(q, v_frd):
    # rotating a body vector in PX4 frames == converting, rotating in pybullet frames, converting back
    q_ned_frd = frames.quat_enu_flu_to_ned_frd(q)
    via_px4 = frames.quat_rotate(q_ned_frd, v_frd)
    via_pybullet = frames.enu_to_ned(frames.quat_rotate(q, frames.frd_to_flu(v_frd)))
    assert np.allclose(via_px4, via_pybullet, atol=1e-9 * (1 + np.linalg.norm(v_frd)))


@settings(deadline=None)  # a busy shared machine must not fail a property
@given(quaternions, vectors)
def test_rotate_and_inverse_rotate_round_trip(q, v):
    assert np.allclose(frames.quat_rotate_inverse(q, frames.quat_rotate(q, v)), v, atol=1e-9 * (1 + np.linalg.norm(v)))
    assert np.allclose(frames.quat_to_matrix(q) @ np.array(v), frames.quat_rotate(q, v), atol=1e-9 * (1 + np.linalg.norm(v)))


@settings(deadline=None)  # a busy shared machine must not fail a property
@given(angles, st.floats(min_value=-1.5, max_value=1.5), angles)
def test_euler_round_trip(roll, pitch, yaw):
    q = frames.quat_from_euler(roll, pitch, yaw)
    back = frames.quat_to_euler(q)
    for got, want in zip(back, (roll, pitch, yaw), strict=True):
        assert abs(frames.wrap_pi(got - want)) < 1e-9  # roll/yaw of +pi and -pi are the same angle
    assert math.isclose(np.linalg.norm(q), 1.0)


@settings(deadline=None)  # a busy shared machine must not fail a property
@given(angles)
def test_yaw_conventions_round_trip(yaw):
    assert math.isclose(frames.wrap_pi(frames.yaw_ned_to_enu(frames.yaw_enu_to_ned(yaw)) - yaw), 0.0, abs_tol=1e-9)


def test_known_attitudes():
    # level, facing east in ENU (yaw 0) is PX4 yaw +90 deg (east of north)
    q = frames.yaw_quaternion_enu_flu(0.0)
    assert np.allclose(frames.quat_to_euler(frames.quat_enu_flu_to_ned_frd(q)), (0, 0, math.pi / 2))
    # facing north in ENU (yaw 90 deg) is PX4 identity attitude
    q = frames.yaw_quaternion_enu_flu(math.pi / 2)
    assert same_rotation(frames.quat_enu_flu_to_ned_frd(q), (1, 0, 0, 0))
    # pybullet order round trip
    assert np.allclose(frames.quaternion_from_pybullet(frames.quaternion_to_pybullet((0.1, 0.2, 0.3, 0.4))),
                       (0.1, 0.2, 0.3, 0.4))


@settings(max_examples=50, deadline=None)
@given(angles)
def test_wrap_pi_range(a):
    w = frames.wrap_pi(a * 7.3)
    assert -math.pi < w <= math.pi
    assert math.isclose(math.sin(w), math.sin(a * 7.3), abs_tol=1e-9)
