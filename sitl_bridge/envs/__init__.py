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
from typing import Any

import gymnasium as gym

from sitl_bridge.autopilot import registry
from sitl_bridge.data_paths import worlds_dir
from sitl_bridge.envs.backends import Backend, BackendError, Snapshot, make_backend
from sitl_bridge.envs.options import ESTIMATORS, EnvOptions
from sitl_bridge.envs.parallel import SitlParallelEnv
from sitl_bridge.envs.runner import OUTCOMES
from sitl_bridge.envs.scenario import Scenario, load_scenario
from sitl_bridge.envs.single import SitlEnv
from sitl_bridge.envs.vector import make_vec_env

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


def make_env(scenario: str | Path, *, drone: int = 0, options: EnvOptions | None = None,
             **option_values: Any) -> SitlEnv:
    """A single-drone Gymnasium env for a scenario file or registered id (see `SitlEnv`).

    The keyword arguments are `EnvOptions` fields (`autopilot="direct"`, `speed_factor`,
    `seed`, `instance_base`, `px4_bin`, `gui`, `estimator`), or pass `options=` whole.
    `estimator="ground_truth"` is the labelled speed shortcut (no sensor simulation or fusion
    in `direct`); the default `"sensors"` is the realistic one (see `ESTIMATORS`)."""
    return SitlEnv(scenario_path(scenario), drone=drone, options=EnvOptions.of(options, **option_values))


def make_parallel_env(scenario: str | Path, *, options: EnvOptions | None = None,
                      **option_values: Any) -> SitlParallelEnv:
    """A PettingZoo ParallelEnv for a scenario file or id (see `SitlParallelEnv`); options
    as for `make_env`."""
    return SitlParallelEnv(scenario_path(scenario), options=EnvOptions.of(options, **option_values))


def __getattr__(name: str) -> Any:
    if name == "AUTOPILOTS":  # the kinds envs run on, as registered now
        return registry.names(env=True)
    raise AttributeError(name)


def _register() -> None:
    for env_id, filename in SINGLE_ENVS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point="sitl_bridge.envs.single:SitlEnv",
                         kwargs={"scenario": str(worlds_dir() / filename)})


_register()

__all__ = [
    "AUTOPILOTS", "ESTIMATORS", "OUTCOMES", "PARALLEL_ENVS", "SINGLE_ENVS", "Backend", "BackendError",
    "EnvOptions", "Scenario", "SitlEnv", "SitlParallelEnv", "Snapshot", "load_scenario", "make_backend",
    "make_env", "make_parallel_env", "make_vec_env", "scenario_path", "worlds_dir",
]
