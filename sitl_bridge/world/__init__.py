"""Worlds as data: the `world:` schema of scenario files, its loader, and per-episode layouts."""

from sitl_bridge.world.layout import GoalPlacement, Layout, ObstaclePlacement, realize
from sitl_bridge.world.loader import load_world, parse_scenario
from sitl_bridge.world.lookup import default_world_path, resolve_world, with_vehicle_count
from sitl_bridge.world.schema import (
    AlongPath,
    Encounter,
    EncounterType,
    GeoHome,
    GoalRegion,
    LidarConfig,
    Obstacle,
    ObstacleRandomization,
    Opening,
    PatrolMover,
    PhysicsSettings,
    RandomLegsMover,
    Shape,
    Spawn,
    VehicleSpec,
    Workspace,
    World,
)

__all__ = [
    "AlongPath", "Encounter", "EncounterType", "GeoHome", "GoalPlacement", "GoalRegion", "Layout", "LidarConfig", "Obstacle",
    "ObstaclePlacement", "ObstacleRandomization", "Opening", "PatrolMover", "PhysicsSettings",
    "RandomLegsMover", "Shape", "Spawn", "VehicleSpec", "Workspace", "World", "default_world_path",
    "load_world", "parse_scenario", "realize", "resolve_world", "with_vehicle_count",
]
