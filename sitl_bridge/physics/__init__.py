"""Physics: the pybullet `Simulation`, the Iris quadrotor model, movers and collisions."""

from sitl_bridge.physics.iris import IrisParams, RotorSet
from sitl_bridge.physics.simulation import (
    Collision,
    MotorCommand,
    PhysicsError,
    Simulation,
    VehicleState,
)

__all__ = ["Collision", "IrisParams", "MotorCommand", "PhysicsError", "RotorSet", "Simulation", "VehicleState"]
