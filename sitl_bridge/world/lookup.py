"""Finding world files by name, and fitting a world to a vehicle count."""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

from sitl_bridge.data_paths import worlds_dirs
from sitl_bridge.errors import ConfigError
from sitl_bridge.world.schema import Spawn, World

DEFAULT_WORLD = "empty"
EXTRA_VEHICLE_SPACING_M = 3.0
"""`with_vehicle_count` beyond the world's: copies of its last vehicle, this far apart (east)."""


def resolve_world(name_or_path: str | os.PathLike[str]) -> Path:
    """A world file from a path, or a bare name (`empty`, `window.yaml`) in `worlds_dirs()`."""
    path = Path(name_or_path)
    if path.is_file():
        return path
    candidates = [path.name, f"{path.name}.yaml"] if path.suffix == "" else [path.name]
    if path.parent == Path("."):
        for directory in worlds_dirs():
            for candidate in candidates:
                if (directory / candidate).is_file():
                    return directory / candidate
    searched = ", ".join(str(d) for d in worlds_dirs()) or "no worlds/ directory found"
    raise ConfigError(f"{name_or_path}: cannot find world file (searched {searched})")


def world_file(name_or_path: str | os.PathLike[str]) -> str | os.PathLike[str]:
    """What a command should open for a scenario argument: a shipped world by bare name
    (`obstacle`, `obstacle.yaml`) through `resolve_world` when no such file is here, else the
    argument itself (a path with folders, or one the OS refuses, is left for the reader to
    report on)."""
    path = Path(name_or_path)
    try:
        if path.is_file() or path.parent != Path("."):
            return name_or_path
    except (OSError, ValueError):  # a name too long for the OS, an embedded NUL: the reader says so
        return name_or_path
    return resolve_world(path)


def default_world_path() -> Path:
    """worlds/empty.yaml of this installation (works from any working directory)."""
    return resolve_world(DEFAULT_WORLD)


def with_vehicle_count(world: World, count: int) -> World:
    """The world with exactly `count` vehicles: extra ones copy the last vehicle's spawn,
    shifted east by `EXTRA_VEHICLE_SPACING_M` each; surplus ones are dropped."""
    if count < 1:
        raise ConfigError(f"{world.source}: vehicles: expected at least 1, got {count}")
    if world.encounter is not None and count != world.encounter.drones:
        raise ConfigError(f"{world.source}: world.encounter.drones: the encounter places {world.encounter.drones} "
                          f"drones every episode, not {count} (change drones: in the file)")
    vehicles = list(world.vehicles[:count])
    if not vehicles:
        raise ConfigError(f"{world.source}: world.vehicles: expected at least 1 vehicle to copy, got none")
    template = vehicles[-1]
    for k in range(1, count - len(vehicles) + 1):
        x, y, z = template.spawn.position_m
        spawn: Spawn = replace(template.spawn, position_m=(x + k * EXTRA_VEHICLE_SPACING_M, y, z))
        vehicles.append(replace(template, name=f"{template.name}_{k}", spawn=spawn))
    return replace(world, vehicles=tuple(vehicles))


__all__ = ["DEFAULT_WORLD", "EXTRA_VEHICLE_SPACING_M", "default_world_path", "resolve_world", "with_vehicle_count",
           "world_file"]
