"""Unit tests of the stub's pieces: mixer, parameters, modes, quaternion math, attitude setpoints."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from sitl_bridge.autopilot.stub.control import body_z_to_attitude
from sitl_bridge.autopilot.stub.mixer import QuadGeometry, QuadXMixer
from sitl_bridge.autopilot.stub.modes import (
    HOLD,
    LAND,
    OFFBOARD,
    TAKEOFF,
    custom_mode,
    split_custom_mode,
)
from sitl_bridge.autopilot.stub.params import (
    MAV_PARAM_TYPE_INT32,
    MAV_PARAM_TYPE_REAL32,
    ParamTable,
    decode_param_value,
    encode_param_value,
    read_params_file,
)
from sitl_bridge.autopilot.stub.vec import (
    quat_from_euler,
    quat_multiply,
    quat_rotate,
    quat_rotate_inverse,
    quat_to_euler,
)
from sitl_bridge.physics import IrisParams


def test_mixer_hover_output_matches_the_iris_hover_input() -> None:
    mixer = QuadXMixer()
    motors = mixer.mix(QuadGeometry().hover_thrust, (0.0, 0.0, 0.0))
    assert motors == pytest.approx((IrisParams().hover_input(),) * 4, abs=0.02)
    assert motors[0] == pytest.approx(0.71, abs=0.02)


def test_mixer_torque_signs_follow_px4_motor_order() -> None:
    mixer = QuadXMixer()
    hover = QuadGeometry().hover_thrust
    m1, m2, m3, m4 = mixer.mix(hover, (0.1, 0.0, 0.0))   # roll right: left motors (2, 3) push
    assert m2 > m1 and m3 > m4
    m1, m2, m3, m4 = mixer.mix(hover, (0.0, 0.1, 0.0))   # pitch up: front motors (1, 3) push
    assert m1 > m2 and m3 > m4
    m1, m2, m3, m4 = mixer.mix(hover, (0.0, 0.0, 0.1))   # yaw right: CCW rotors (1, 2) push
    assert m1 > m3 and m2 > m4


@given(thrust=st.floats(-0.5, 1.5), roll=st.floats(-3, 3), pitch=st.floats(-3, 3), yaw=st.floats(-3, 3))
def test_mixer_outputs_stay_in_unit_range(thrust: float, roll: float, pitch: float, yaw: float) -> None:
    motors = QuadXMixer().mix(thrust, (roll, pitch, yaw))
    assert all(0.0 <= u <= 1.0 for u in motors)


def test_custom_modes_are_px4s() -> None:
    assert custom_mode(*HOLD) == 50593792
    assert custom_mode(*TAKEOFF) == 33816576
    assert custom_mode(*LAND) == 100925440
    assert custom_mode(*OFFBOARD) == 393216
    assert split_custom_mode(50593792) == (4, 3)


@given(st.integers(-(2**31), 2**31 - 1))
def test_int32_params_travel_bytewise(value: int) -> None:
    raw = encode_param_value(value, MAV_PARAM_TYPE_INT32)
    assert raw == struct.pack("<i", value)   # even when those bits are a signalling NaN
    assert decode_param_value(raw, MAV_PARAM_TYPE_INT32) == value


def test_real32_params_travel_as_floats() -> None:
    assert encode_param_value(2.5, MAV_PARAM_TYPE_REAL32) == struct.pack("<f", 2.5)
    assert decode_param_value(struct.pack("<f", 2.5), MAV_PARAM_TYPE_REAL32) == 2.5


def test_param_table_has_px4_names_and_types() -> None:
    table = ParamTable(px4_params_dir=None)
    assert table.get("MIS_TAKEOFF_ALT").param_type == MAV_PARAM_TYPE_REAL32
    assert table.get("CAL_ACC0_ID").param_type == MAV_PARAM_TYPE_INT32 and table["CAL_ACC0_ID"] != 0
    assert table.get("SYS_HITL").param_type == MAV_PARAM_TYPE_INT32
    table.set("COM_OBL_RC_ACT", 4.7)
    assert table["COM_OBL_RC_ACT"] == 4.0   # INT32 truncates
    with pytest.raises(KeyError):
        table.set("NOT_A_PARAM", 1.0)
    assert [p.name for p in table][table.index_of("MPC_XY_P")] == "MPC_XY_P"
    assert table.at(len(table)) is None


def test_params_files_both_formats_and_wall_timeouts(tmp_path: Path) -> None:
    (tmp_path / "a.params").write_text(
        "# comment\n"
        "COM_OF_LOSS_T 1.5 wall 20   # a wall-clock timeout\n"
        "COM_OBL_RC_ACT 4\n"
        "MY_NEW_PARAM 0.25\n"
        "broken line here with words\n"
    )
    (tmp_path / "b.params").write_text("1\t1\tMIS_TAKEOFF_ALT\t3.0\t9\n1\t1\tMY_INT\t7\t6\n")
    entries = list(read_params_file(tmp_path / "a.params"))
    assert [e.name for e in entries] == ["COM_OF_LOSS_T", "COM_OBL_RC_ACT", "MY_NEW_PARAM"]
    assert entries[0].wall and entries[0].wall_max == 20
    table = ParamTable(px4_params_dir=tmp_path, speed_factor=30.0)
    assert table["COM_OF_LOSS_T"] == 20.0          # 1.5 s x 30, capped at 20
    assert table["COM_OBL_RC_ACT"] == 4 and table.get("COM_OBL_RC_ACT").param_type == MAV_PARAM_TYPE_INT32
    assert table["MIS_TAKEOFF_ALT"] == 3.0
    assert table.get("MY_INT").param_type == MAV_PARAM_TYPE_INT32 and table["MY_INT"] == 7
    assert table.get("MY_NEW_PARAM").param_type == MAV_PARAM_TYPE_REAL32
    assert ParamTable(px4_params_dir=tmp_path)["COM_OF_LOSS_T"] == 1.5   # no speed factor: unscaled


@given(st.floats(-3.0, 3.0), st.floats(-1.5, 1.5), st.floats(-3.1, 3.1))
def test_euler_quaternion_round_trip(roll: float, pitch: float, yaw: float) -> None:
    q = quat_from_euler(roll, pitch, yaw)
    r, p, y = quat_to_euler(q)
    again = quat_from_euler(r, p, y)
    assert abs(sum(a * b for a, b in zip(q, again, strict=True))) == pytest.approx(1.0, abs=1e-9)
    v = (0.3, -1.2, 2.0)
    assert quat_rotate_inverse(q, quat_rotate(q, v)) == pytest.approx(v, abs=1e-9)


def test_quaternion_rotation_conventions() -> None:
    yaw90 = quat_from_euler(0.0, 0.0, math.pi / 2)
    assert quat_rotate(yaw90, (1.0, 0.0, 0.0)) == pytest.approx((0.0, 1.0, 0.0), abs=1e-12)  # nose north -> east
    both = quat_multiply(yaw90, yaw90)
    assert quat_to_euler(both)[2] == pytest.approx(math.pi, abs=1e-9) or \
        quat_to_euler(both)[2] == pytest.approx(-math.pi, abs=1e-9)


@given(st.floats(-0.7, 0.7), st.floats(-0.7, 0.7), st.floats(-3.1, 3.1))
def test_body_z_to_attitude_points_thrust_and_keeps_heading(x: float, y: float, yaw: float) -> None:
    body_z = (x, y, 1.0)
    q = body_z_to_attitude(body_z, yaw)
    n = math.sqrt(x * x + y * y + 1.0)
    assert quat_rotate(q, (0.0, 0.0, 1.0)) == pytest.approx((x / n, y / n, 1.0 / n), abs=1e-9)
    forward = quat_rotate(q, (1.0, 0.0, 0.0))
    assert math.atan2(forward[1], forward[0]) == pytest.approx(yaw, abs=0.35)
