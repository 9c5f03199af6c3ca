"""The typed records the simulation hands out: motor commands in, vehicle state and collisions out."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from sitl_bridge.frames import (
    enu_to_ned_xyz,
    flu_to_frd_xyz,
    quat_enu_flu_to_ned_frd_t,
    quat_to_euler_t,
)


@dataclass(frozen=True)
class MotorCommand:
    """Motor inputs of one vehicle for one step (what HIL_ACTUATOR_CONTROLS carries)."""

    controls: tuple[float, float, float, float]  # PX4 motors 1..4 (quad-X order), each in [0, 1]
    armed: bool                                  # False -> rotors spin down to 0

    @staticmethod
    def disarmed() -> MotorCommand:
        """All motors off, disarmed."""
        return _DISARMED


_DISARMED = MotorCommand((0.0, 0.0, 0.0, 0.0), False)
_new_object = object.__new__
_set_field = object.__setattr__


def armed_command(controls: tuple[float, float, float, float]) -> MotorCommand:
    """MotorCommand(controls, True) without the frozen dataclass's checked __init__: for the
    per-step paths (the stub's outputs, the HIL link's actuator messages)."""
    command = _new_object(MotorCommand)
    _set_field(command, "controls", controls)
    _set_field(command, "armed", True)
    return command


@dataclass(frozen=True)
class Collision:
    """One contact reported for the last step.

    kind: "obstacle" (other = obstacle name), "vehicle" (other = the other vehicle's name) or
    "ground" (other = "ground"; only hard contacts: faster than the world's
    `hard_ground_speed_m_s` or tilted beyond `crash_tilt_deg`, so resting/landing is not one).
    """

    vehicle: int
    kind: str
    other: str
    speed_m_s: float
    time_us: int


# One vehicle's state vector (float64), as `Simulation` keeps it and the compiled per-step
# kernels read it: the six `VehicleState.raw` groups in their order, then what the rotor model
# needs (the body-to-world rotation matrix, row-major, and the world angular velocity).
POS, QUAT, VEL, OMEGA_FLU, FORCE_FLU, ACCEL, ROT, OMEGA_WORLD = 0, 3, 7, 10, 13, 16, 19, 28
STATE_SIZE = 31
RAW_SIZE = ROT
"""The leading part that `VehicleState.raw` covers (position ... acceleration)."""


def _readonly(values) -> np.ndarray:
    array = np.array(values, dtype=float)
    array.flags.writeable = False
    return array


class VehicleState:
    """Vehicle state after a step: world ENU, body FLU; NED/FRD views as properties.

    Immutable. The arrays are built on first access from the plain-float tuples in `raw`
    (position, quaternion, velocity, angular velocity, specific force, acceleration), which
    per-step consumers such as `SensorSuite` read directly to skip numpy.
    """

    def __init__(self, position_enu_m, quaternion_enu_flu, velocity_enu_m_s, angular_velocity_flu_rad_s,
                 specific_force_flu_m_s2, rotor_speeds_rad_s, acceleration_enu_m_s2=(0.0, 0.0, 0.0),
                 on_ground: bool = False) -> None:
        def floats(values) -> tuple[float, ...]:
            return tuple(float(c) for c in values)

        self.__dict__["raw"] = (
            floats(position_enu_m), floats(quaternion_enu_flu), floats(velocity_enu_m_s),
            floats(angular_velocity_flu_rad_s), floats(specific_force_flu_m_s2), floats(acceleration_enu_m_s2))
        self._rotor_speeds = floats(rotor_speeds_rad_s)
        self.on_ground = bool(on_ground)  # touching the ground plane this step

    @classmethod
    def _from_tuples(cls, raw: tuple, rotor_speeds: tuple[float, ...], on_ground: bool) -> VehicleState:
        state = cls.__new__(cls)
        state.raw = raw
        state._rotor_speeds = rotor_speeds
        state.on_ground = on_ground
        return state

    @classmethod
    def _from_vector(cls, vector: np.ndarray, rotor_speeds: tuple[float, ...], on_ground: bool) -> VehicleState:
        """From a private copy of the simulation's state vector (`raw` is built on first use)."""
        state = cls.__new__(cls)
        state.__dict__["vector"] = vector
        state._rotor_speeds = rotor_speeds
        state.on_ground = on_ground
        return state

    @cached_property
    def raw(self) -> tuple[tuple[float, ...], ...]:  # set directly unless built from a vector
        """(position, quaternion, velocity, angular velocity, specific force, acceleration) as
        plain-float tuples (ENU / FLU)."""
        v = self.vector.tolist()
        return (tuple(v[0:3]), tuple(v[3:7]), tuple(v[7:10]), tuple(v[10:13]), tuple(v[13:16]), tuple(v[16:19]))

    @cached_property
    def vector(self) -> np.ndarray:
        """The `raw` groups as one float64 vector (the layout at the top of this module), for the
        compiled kernels (`SensorSuite`). Do not modify it."""
        vector = np.zeros(RAW_SIZE)
        for start, values in zip((POS, QUAT, VEL, OMEGA_FLU, FORCE_FLU, ACCEL), self.raw, strict=True):
            vector[start:start + len(values)] = values
        return vector

    def __repr__(self) -> str:
        names = ("position_enu_m", "quaternion_enu_flu", "velocity_enu_m_s", "angular_velocity_flu_rad_s",
                 "specific_force_flu_m_s2", "acceleration_enu_m_s2")
        parts = [f"{n}={tuple(round(c, 4) for c in r)}" for n, r in zip(names, self.raw, strict=True)]
        return f"VehicleState({', '.join(parts)}, on_ground={self.on_ground})"

    # -- contract fields (ENU / FLU) --------------------------------------------------------
    @cached_property
    def position_enu_m(self) -> np.ndarray:
        return _readonly(self.raw[0])

    @cached_property
    def quaternion_enu_flu(self) -> np.ndarray:
        """(w, x, y, z), rotates FLU vectors into ENU."""
        return _readonly(self.raw[1])

    @cached_property
    def velocity_enu_m_s(self) -> np.ndarray:
        return _readonly(self.raw[2])

    @cached_property
    def angular_velocity_flu_rad_s(self) -> np.ndarray:
        return _readonly(self.raw[3])

    @cached_property
    def specific_force_flu_m_s2(self) -> np.ndarray:
        """What an ideal accelerometer reads (at rest: +g along body up)."""
        return _readonly(self.raw[4])

    @cached_property
    def acceleration_enu_m_s2(self) -> np.ndarray:
        """Coordinate acceleration over the last step (extension of the contract)."""
        return _readonly(self.raw[5])

    @cached_property
    def rotor_speeds_rad_s(self) -> np.ndarray:
        """PX4 motor order 1..4."""
        return _readonly(self._rotor_speeds)

    # -- PX4 views (NED / FRD) ---------------------------------------------------------------
    @cached_property
    def position_ned_m(self) -> np.ndarray:
        return _readonly(enu_to_ned_xyz(*self.raw[0]))

    @cached_property
    def velocity_ned_m_s(self) -> np.ndarray:
        return _readonly(enu_to_ned_xyz(*self.raw[2]))

    @cached_property
    def acceleration_ned_m_s2(self) -> np.ndarray:
        return _readonly(enu_to_ned_xyz(*self.raw[5]))

    @cached_property
    def quaternion_ned_frd(self) -> np.ndarray:
        """(w, x, y, z), rotates FRD vectors into NED (PX4's attitude)."""
        return _readonly(quat_enu_flu_to_ned_frd_t(self.raw[1]))

    @cached_property
    def euler_ned_frd_rad(self) -> np.ndarray:
        """(roll, pitch, yaw) as PX4 reports them (yaw from north, clockwise)."""
        return _readonly(quat_to_euler_t(quat_enu_flu_to_ned_frd_t(self.raw[1])))

    @cached_property
    def angular_velocity_frd_rad_s(self) -> np.ndarray:
        return _readonly(flu_to_frd_xyz(*self.raw[3]))

    @cached_property
    def specific_force_frd_m_s2(self) -> np.ndarray:
        return _readonly(flu_to_frd_xyz(*self.raw[4]))
