"""The Iris quadrotor with PX4's Gazebo-classic parameters (`models/iris/iris.sdf.jinja`,
`gazebo_motor_model.cpp`): rigid body, four rotors in PX4 quad-X order, motor lag, thrust,
yaw moment and rotor drag. Pure Python floats: this runs once per vehicle per physics step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

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


class RotorSet:
    """Four rotors' speed state and the body force/torque they produce.

    `wrench` uses the current (previous step's filtered) speeds, as Gazebo's motor model does;
    `update_speeds` then moves them toward the commanded reference with the asymmetric lag.
    """

    def __init__(self, params: IrisParams, step_s: float) -> None:
        self.params = params
        self.speeds_rad_s = [0.0, 0.0, 0.0, 0.0]
        self._alpha_up = math.exp(-step_s / params.time_constant_up_s)
        self._alpha_down = math.exp(-step_s / params.time_constant_down_s)
        self._positions = params.rotor_positions_flu_m
        self._yaw_moment = tuple(-d * params.moment_constant_m for d in params.rotor_directions)
        # constants of the per-step path, unpacked once (attribute look-ups cost more than the math)
        self._roll_arms = tuple(r[1] for r in self._positions)     # torque x = sum(y_i T_i)
        self._pitch_arms = tuple(-r[0] for r in self._positions)   # torque y = -sum(x_i T_i)
        self._kf = params.motor_constant_n_s2
        self._inv_max_airspeed = 1.0 / params.max_relative_airspeed_m_s
        self._drag = -params.rotor_drag_coefficient
        self._map = (params.input_scaling_rad_s, params.zero_position_armed_rad_s, params.max_rotor_speed_rad_s)

    def reset(self) -> None:
        self.speeds_rad_s = [0.0, 0.0, 0.0, 0.0]

    def step(self, controls: tuple[float, ...], armed: bool, velocity_flu_m_s: Vec3) -> tuple[Vec3, Vec3]:
        """One physics step: the wrench from the current speeds, then the speeds' update."""
        wrench = self.wrench(velocity_flu_m_s)
        self.update_speeds(controls, armed)
        return wrench

    def update_speeds(self, controls: tuple[float, ...], armed: bool) -> None:
        """Advance the motor lag one step toward omega_ref = 1000 u + 100 (armed) or 0."""
        speeds = self.speeds_rad_s
        up, down = self._alpha_up, self._alpha_down
        scale, zero, top = self._map
        for i in range(4):
            if armed:
                u = controls[i]
                u = u if u > 0.0 else 0.0  # also maps NaN to 0: a bad command must not explode the physics
                u = 1.0 if u > 1.0 else u
                ref = u * scale + zero
                if ref > top:
                    ref = top
            else:
                ref = 0.0
            w = speeds[i]
            alpha = up if ref > w else down
            speeds[i] = alpha * w + (1.0 - alpha) * ref

    def wrench(self, velocity_flu_m_s: Vec3) -> tuple[Vec3, Vec3]:
        """(force, torque) on the body in FLU at the centre of mass, from thrust, yaw moment and drag."""
        vx, vy, vz = velocity_flu_m_s
        # thrust fades with axial airspeed (Gazebo's maxRelativeAirspeed scaling)
        fade = 1.0 - abs(vz) * self._inv_max_airspeed
        kf = self._kf * fade if fade > 0.0 else 0.0
        # unrolled over the four rotors: this runs every physics step
        w0, w1, w2, w3 = self.speeds_rad_s
        t0, t1, t2, t3 = kf * w0 * w0, kf * w1 * w1, kf * w2 * w2, kf * w3 * w3
        x0, x1, x2, x3 = self._roll_arms
        y0, y1, y2, y3 = self._pitch_arms
        z0, z1, z2, z3 = self._yaw_moment
        # rotor drag opposes the velocity perpendicular to the rotor axes (applied at the CoM:
        # the moment from the 2 cm rotor height and the 1e-6 rolling moment are negligible)
        drag = self._drag * (w0 + w1 + w2 + w3)
        return ((drag * vx, drag * vy, t0 + t1 + t2 + t3),
                (x0 * t0 + x1 * t1 + x2 * t2 + x3 * t3, y0 * t0 + y1 * t1 + y2 * t2 + y3 * t3,
                 z0 * t0 + z1 * t1 + z2 * t2 + z3 * t3))
