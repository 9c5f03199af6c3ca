"""Gymnasium and PettingZoo environments over the scenario files in `worlds/`.

```python
import gymnasium as gym
import sitl_bridge.envs  # registers the ids below

env = sitl_bridge.envs.make_env("worlds/random_goal.yaml", autopilot="direct", seed=0)
env = gym.make("sitl_bridge/RandomGoal-v0", autopilot="stub", speed_factor=0)
penv = sitl_bridge.envs.make_parallel_env("sitl_bridge/TwoDronesEmpty-v0")  # PettingZoo
```

A scenario is a file path or a registered id. Registered ids resolve to files in the worlds
directory (`$SITL_BRIDGE_WORLDS`, else the `worlds/` folder of the source tree).
"""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym

from sitl_bridge.data_paths import worlds_dir
from sitl_bridge.envs.backends import (
    AUTOPILOTS,
    ESTIMATORS,
    Backend,
    BackendError,
    Snapshot,
    make_backend,
)
from sitl_bridge.envs.parallel import SitlParallelEnv
from sitl_bridge.envs.runner import OUTCOMES
from sitl_bridge.envs.scenario import Scenario, load_scenario
from sitl_bridge.envs.single import SitlEnv

SINGLE_ENVS: dict[str, str] = {
    "sitl_bridge/Empty-v0": "empty.yaml",
    "sitl_bridge/RandomGoal-v0": "random_goal.yaml",
    "sitl_bridge/Obstacle-v0": "obstacle.yaml",
    "sitl_bridge/RandomObstacle-v0": "random_obstacle.yaml",
    "sitl_bridge/Window-v0": "window.yaml",
    "sitl_bridge/Street-v0": "street.yaml",
}
"""Gymnasium ids of the single-drone scenarios (thesis E, ER, O, OR, W and the street)."""

PARALLEL_ENVS: dict[str, str] = {
    "sitl_bridge/TwoDronesEmpty-v0": "two_drones_empty.yaml",
    "sitl_bridge/TwoDronesWindow-v0": "two_drones_window.yaml",
}
"""Ids of the multi-drone scenarios (thesis TE, TW) for `make_parallel_env`."""


def scenario_path(scenario: str | Path) -> Path:
    """A registered id's file, or `scenario` itself when it is a path."""
    text = str(scenario)
    name = SINGLE_ENVS.get(text) or PARALLEL_ENVS.get(text)
    return worlds_dir() / name if name else Path(scenario)


def make_env(scenario: str | Path, *, autopilot: str = "direct", speed_factor: float = 0.0,
             seed: int | None = None, drone: int = 0, instance_base: int = 0,
             px4_bin: str | None = None, gui: bool = False, estimator: str = "sensors") -> SitlEnv:
    """A single-drone Gymnasium env for a scenario file or registered id (see `SitlEnv`).

    `estimator="ground_truth"` is the labelled speed shortcut (no sensor simulation or fusion
    in `direct`); the default `"sensors"` is the realistic one (see `ESTIMATORS`)."""
    return SitlEnv(scenario_path(scenario), autopilot=autopilot, speed_factor=speed_factor,
                   seed=seed, drone=drone, instance_base=instance_base, px4_bin=px4_bin, gui=gui,
                   estimator=estimator)


def make_parallel_env(scenario: str | Path, *, autopilot: str = "direct",
                      speed_factor: float = 0.0, seed: int | None = None,
                      instance_base: int = 0, px4_bin: str | None = None,
                      gui: bool = False, estimator: str = "sensors") -> SitlParallelEnv:
    """A PettingZoo ParallelEnv for a scenario file or id (see `SitlParallelEnv`)."""
    return SitlParallelEnv(scenario_path(scenario), autopilot=autopilot,
                           speed_factor=speed_factor, seed=seed, instance_base=instance_base,
                           px4_bin=px4_bin, gui=gui, estimator=estimator)


def _register() -> None:
    for env_id, filename in SINGLE_ENVS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point="sitl_bridge.envs.single:SitlEnv",
                         kwargs={"scenario": str(worlds_dir() / filename)})


_register()

__all__ = [
    "AUTOPILOTS", "ESTIMATORS", "OUTCOMES", "PARALLEL_ENVS", "SINGLE_ENVS", "Backend", "BackendError",
    "Scenario", "SitlEnv", "SitlParallelEnv", "Snapshot", "load_scenario", "make_backend",
    "make_env", "make_parallel_env", "scenario_path", "worlds_dir",
]
