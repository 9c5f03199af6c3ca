"""A scenario: one YAML file = `world:` (geometry, read by `sitl_bridge.world`) + `task:` (here).

Adding a scenario never needs code: write a new file with both sections and pass its path to
`make_env` / `make_parallel_env`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sitl_bridge.envs.task import TaskConfig, parse_task
from sitl_bridge.envs.view import ScenarioLimits
from sitl_bridge.errors import ConfigError
from sitl_bridge.sensors.lidar import ray_labels
from sitl_bridge.world import World, load_world


@dataclass(frozen=True)
class Scenario:
    """A loaded world and its parsed task."""

    world: World
    task: TaskConfig
    limits: ScenarioLimits

    @property
    def name(self) -> str:
        return self.world.name

    @property
    def num_drones(self) -> int:
        return self.world.num_vehicles


def limits_of(world: World) -> ScenarioLimits:
    """Observation bounds of `world` (workspace, lidar layout of its first vehicle)."""
    lidar = world.vehicles[0].lidar
    return ScenarioLimits(
        num_drones=world.num_vehicles,
        workspace_low_enu_m=np.asarray(world.workspace.min_m, dtype=float),
        workspace_high_enu_m=np.asarray(world.workspace.max_m, dtype=float),
        lidar_rays={"horizontal": lidar.horizontal_rays, "up": lidar.up_rays, "down": lidar.down_rays},
        lidar_range_m=lidar.range_m,
        lidar_labels=ray_labels(lidar),
    )


def load_scenario(path: str | Path) -> Scenario:
    """Load `path` (world + task); a bad file raises a one-line `ConfigError`."""
    world = load_world(path)
    if world.num_vehicles < 1:
        raise ConfigError(f"{world.source}: world.vehicles: expected at least 1 vehicle for an env, got 0")
    for i, vehicle in enumerate(world.vehicles):
        if vehicle.goal is None:
            raise ConfigError(f"{world.source}: world.vehicles[{i}].goal: expected a goal for "
                              "every vehicle of a scenario, got none")
    if world.task is None:
        raise ConfigError(f"{world.source}: task: required section is missing")
    limits = limits_of(world)
    return Scenario(world=world, task=parse_task(world.task, limits), limits=limits)
