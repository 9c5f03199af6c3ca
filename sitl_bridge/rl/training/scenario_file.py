"""One check of a whole scenario file: `world:` (with its geometry sense), `task:` and `train:`.

`sitl-bridge worlds check`, `train`, `curriculum` and the sweep runner all call this before
they start anything, so a typo in any section is a one-line error at once, not a failure after
the simulator (or a run directory) was created.
"""

from __future__ import annotations

from pathlib import Path

from sitl_bridge.envs.scenario import load_scenario
from sitl_bridge.rl.learner.config import parse_train_node
from sitl_bridge.world import World, load_world


def check_scenario_file(path: str | Path, *, need_task: bool = False) -> World:
    """Validate every section present in `path` (`task:` required with `need_task`); raises a
    one-line `ConfigError` naming file and key; returns the world."""
    world = load_world(path)
    if world.task is not None or need_task:
        load_scenario(path)
    if world.train is not None:
        parse_train_node(world.train)
    return world
