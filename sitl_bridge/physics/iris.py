"""The Iris quadrotor with PX4's Gazebo-classic parameters (`models/iris/iris.sdf.jinja`,
`gazebo_motor_model.cpp`): rigid body, four rotors in PX4 quad-X order, motor lag, thrust,
yaw moment and rotor drag. The per-step math is a compiled kernel (`sitl_bridge.jit`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sitl_bridge.jit import kernel

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class IrisParams:
    """Gazebo iris parameters (see the PX4 protocol fact sheet, part A6)."""

    mass_kg: float = 1.5 + 0.015 + 0.015 + 4 * 0.005   # base + IMU + GPS + rotors
    inertia_kg_m2: Vec3 = (0.029125, 0.029125, 0.055225)
    collision_box_m: Vec3 = (0.47, 0.47, 0.11)
    #: Rotor positions in body FLU (m), PX4 motors 1..4 = Gazebo rotor_0..3.
    rotor_positions_flu_m: tuple[Vec3, ...] = (
        (0.13, -0.22, 0.023),   # motor 1, front right, CCW
        (-0.13, 0.20, 0.023),   # motor 2, back left, CCW
        (0.13, 0.22, 0.023),    # motor 3, front left, CW
        (-0.13, -0.20, 0.023),  # motor 4, back right, CW
    )
    #: +1 = counter-clockwise seen from above (PX4 KM > 0), -1 = clockwise.
    rotor_directions: tuple[int, ...] = (1, 1, -1, -1)
    motor_constant_n_s2: float = 5.84e-6        # thrust = k_f * omega^2
    moment_constant_m: float = 0.06             # yaw moment = k_m * thrust
    max_rotor_speed_rad_s: float = 1100.0
    input_scaling_rad_s: float = 1000.0         # omega_ref = u * scaling + zero_position_armed
    zero_position_armed_rad_s: float = 100.0
    time_constant_up_s: float = 0.0125
    time_constant_down_s: float = 0.025
    rotor_drag_coefficient: float = 1.75e-4     # N per (rad/s * m/s), perpendicular to the rotor axis
    max_relative_airspeed_m_s: float = 25.0     # thrust fades to 0 at this axial airspeed

    def hover_rotor_speed_rad_s(self, gravity_m_s2: float = 9.8066) -> float:
        """Rotor speed (same on all four) whose thrust balances the weight."""
        return math.sqrt(self.mass_kg * gravity_m_s2 / (4.0 * self.motor_constant_n_s2))

    def hover_input(self, gravity_m_s2: float = 9.8066) -> float:
        """Motor input u (same on all four) whose thrust balances the weight."""
        omega = self.hover_rotor_speed_rad_s(gravity_m_s2)
        return (omega - self.zero_position_armed_rad_s) / self.input_scaling_rad_s


# RotorSet.constants layout (see `rotor_wrench` / `rotor_update_speeds`)
_ALPHA_UP, _ALPHA_DOWN, _SCALE, _ZERO, _TOP, _KF, _INV_AIRSPEED, _DRAG = range(8)
_ROLL_ARMS, _PITCH_ARMS, _YAW_MOMENTS = 8, 12, 16
ROTOR_CONSTANTS = 20


class RotorSet:
    """Four rotors' speed state and the body force/torque they produce.

    `wrench` uses the current (previous step's filtered) speeds, as Gazebo's motor model does;
    `update_speeds` then moves them toward the commanded reference with the asymmetric lag.
    The state (`speeds`) and the constants are float64 arrays for the compiled kernels
    `rotor_wrench` / `rotor_update_speeds`, which these methods call.
    """

    def __init__(self, params: IrisParams, step_s: float) -> None:
        self.params = params
        self.speeds = np.zeros(4)
        k = self.constants = np.zeros(ROTOR_CONSTANTS)
        k[_ALPHA_UP] = math.exp(-step_s / params.time_constant_up_s)
        k[_ALPHA_DOWN] = math.exp(-step_s / params.time_constant_down_s)
        k[_SCALE], k[_ZERO] = params.input_scaling_rad_s, params.zero_position_armed_rad_s
        k[_TOP] = params.max_rotor_speed_rad_s
        k[_KF] = params.motor_constant_n_s2
        k[_INV_AIRSPEED] = 1.0 / params.max_relative_airspeed_m_s
        k[_DRAG] = -params.rotor_drag_coefficient
        positions = params.rotor_positions_flu_m
        k[_ROLL_ARMS:_ROLL_ARMS + 4] = [r[1] for r in positions]      # torque x = sum(y_i T_i)
        k[_PITCH_ARMS:_PITCH_ARMS + 4] = [-r[0] for r in positions]   # torque y = -sum(x_i T_i)
        k[_YAW_MOMENTS:_YAW_MOMENTS + 4] = [-d * params.moment_constant_m for d in params.rotor_directions]

    @property
    def speeds_rad_s(self) -> list[float]:
        """Rotor speeds (rad/s), PX4 motor order; assign a 4-sequence to set them."""
        return self.speeds.tolist()

    @speeds_rad_s.setter
    def speeds_rad_s(self, values) -> None:  # noqa: ANN001 - any 4-sequence of numbers
        self.speeds[:] = [float(w) for w in values]

    def reset(self) -> None:
        self.speeds[:] = 0.0

    def step(self, controls: tuple[float, ...], armed: bool, velocity_flu_m_s: Vec3) -> tuple[Vec3, Vec3]:
        """One physics step: the wrench from the current speeds, then the speeds' update."""
        wrench = self.wrench(velocity_flu_m_s)
        self.update_speeds(controls, armed)
        return wrench

    def update_speeds(self, controls: tuple[float, ...], armed: bool) -> None:
        """Advance the motor lag one step toward omega_ref = 1000 u + 100 (armed) or 0."""
        u0, u1, u2, u3 = (float(u) for u in controls)
        rotor_update_speeds(self.constants, self.speeds, u0, u1, u2, u3, bool(armed))

    def wrench(self, velocity_flu_m_s: Vec3) -> tuple[Vec3, Vec3]:
        """(force, torque) on the body in FLU at the centre of mass, from thrust, yaw moment and drag."""
        vx, vy, vz = (float(v) for v in velocity_flu_m_s)
        fx, fy, fz, tx, ty, tz = rotor_wrench(self.constants, self.speeds, vx, vy, vz)
        return (fx, fy, fz), (tx, ty, tz)


@kernel()
def rotor_wrench(k: np.ndarray, speeds: np.ndarray, vx: float, vy: float, vz: float) -> tuple[float, ...]:
    """(fx, fy, fz, tx, ty, tz) in body FLU from the rotor speeds and the body velocity."""
    # thrust fades with axial airspeed (Gazebo's maxRelativeAirspeed scaling)
    fade = 1.0 - abs(vz) * k[_INV_AIRSPEED]
    kf = k[_KF] * fade if fade > 0.0 else 0.0
    w0, w1, w2, w3 = speeds[0], speeds[1], speeds[2], speeds[3]
    t0, t1, t2, t3 = kf * w0 * w0, kf * w1 * w1, kf * w2 * w2, kf * w3 * w3
    # rotor drag opposes the velocity perpendicular to the rotor axes (applied at the CoM:
    # the moment from the 2 cm rotor height and the 1e-6 rolling moment are negligible)
    drag = k[_DRAG] * (w0 + w1 + w2 + w3)
    r, p, y = _ROLL_ARMS, _PITCH_ARMS, _YAW_MOMENTS
    return (drag * vx, drag * vy, t0 + t1 + t2 + t3,
            k[r] * t0 + k[r + 1] * t1 + k[r + 2] * t2 + k[r + 3] * t3,
            k[p] * t0 + k[p + 1] * t1 + k[p + 2] * t2 + k[p + 3] * t3,
            k[y] * t0 + k[y + 1] * t1 + k[y + 2] * t2 + k[y + 3] * t3)


@kernel()
def rotor_update_speeds(k: np.ndarray, speeds: np.ndarray, u0: float, u1: float, u2: float, u3: float,
                        armed: bool) -> None:
    """Advance the motor lag one step toward omega_ref = scale u + zero (armed) or 0."""
    for i in range(4):
        ref = 0.0
        if armed:
            u = u0 if i == 0 else u1 if i == 1 else u2 if i == 2 else u3
            u = u if u > 0.0 else 0.0  # also maps NaN to 0: a bad command must not explode the physics
            u = 1.0 if u > 1.0 else u
            ref = u * k[_SCALE] + k[_ZERO]
            if ref > k[_TOP]:
                ref = k[_TOP]
        w = speeds[i]
        alpha = k[_ALPHA_UP] if ref > w else k[_ALPHA_DOWN]
        speeds[i] = alpha * w + (1.0 - alpha) * ref
