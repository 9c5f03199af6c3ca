"""`SitlEnv`: the single-drone Gymnasium environment over any scenario file."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from sitl_bridge.client.actions import NUM_ACTIONS
from sitl_bridge.envs.actions import action_space
from sitl_bridge.envs.backends.base import Backend
from sitl_bridge.envs.manual import describe
from sitl_bridge.envs.options import EnvOptions
from sitl_bridge.envs.render import EnvRenderer, FrameList
from sitl_bridge.envs.runner import EpisodeRunner
from sitl_bridge.envs.scenario import Scenario, load_scenario
from sitl_bridge.physics.render import RenderConfig


def observation_space(scenario: Scenario) -> spaces.Box:
    """The Box of one drone's observation: the features' bounds, float32."""
    low = np.concatenate([f.low for f in scenario.task.observation]).astype(np.float32)
    high = np.concatenate([f.high for f in scenario.task.observation]).astype(np.float32)
    return spaces.Box(low=low, high=high, dtype=np.float32)


class SitlEnv(gym.Env[np.ndarray, np.int64]):
    """A drone learns to reach a goal region without colliding, in a scenario of the thesis.

    ## Description
    One quadrotor (PX4's Iris) flies in the world of a scenario file (`worlds/*.yaml`): empty
    space, a static or randomised obstacle, a wall with a window, a street with pedestrians and
    birds. Each step the agent picks one of eight velocity commands; the autopilot (the built-in
    PX4-compatible stub, or real PX4) flies it for a fixed span of simulated time while the
    simulation runs in lockstep, then the simulation is held while the agent decides. The task
    (observation, rewards, episode end, action settings) is the file's `task:` section, so a new
    scenario needs no code. In a world with several drones this env controls drone `drone`; the
    others hover (use `SitlParallelEnv` to control all of them).

    ## Action Space
    `Discrete(8)`, the thesis's table, each a velocity of `task.action.speed_m_s` (1 m/s) held
    for `task.action.duration_s` (1 s) of simulated time, optionally followed by
    `task.action.zero_velocity_s` of hover:

    | code | `frame: world` (default) | `frame: goal` |
    |---|---|---|
    | 0 | east | right of the start-goal direction |
    | 1 | west | left |
    | 2 | south | back |
    | 3 | north | forward (toward the goal, horizontally) |
    | 4 | down | down |
    | 5 | up | up |
    | 6 | toward the goal (straight line, slowed to stop at it) | same |
    | 7 | hover (zero velocity) | same |

    Drones listed in `task.action.swap_drones` have 0/1 and 2/3 swapped (the thesis's fix for a
    drone facing the other way in world frame).

    With `task.action.type: velocity` the action is continuous instead: `Box(-1, 1, (3,),
    float32)` (x, y, z), or `(4,)` with `yaw: rate` (a yaw rate as 4th component), scaled to a
    velocity setpoint of at most `max_speed_m_s` (the norm is capped, not each component) and
    held `duration_s` (any multiple of the physics step, e.g. 0.1 s). Axes per `frame`: `world`
    (east, north, up), `goal` (right, forward of the start-goal direction, up), `body` (right,
    forward of the heading, up). Components are clipped to [-1, 1]; NaN or inf raises
    ValueError. Details: `sitl_bridge.envs.actions`.

    ## Observation Space
    `Box(float32)`: the concatenation of the features listed in `task.observation`, in order,
    in the world ENU frame (x east, y north, z up; m, m/s, rad). Bounds per feature (values are
    clipped to them, never NaN or inf): position and goal in the workspace box; orientation in
    [-pi, pi]; velocities +-5 m/s; lidar in [0, range] (5 m; max range when nothing is hit);
    priorities and flags in [0, 1]; dummy padding always 0 (declared [-1, 1]). The full table
    of features is in `sitl_bridge.envs.features`; `env.describe()` prints the one of the
    loaded scenario.

    ## Rewards
    The sum of the terms in `task.reward`, each `scale * term`, logged by name in
    `info["reward_terms"]`: `closer_to_goal` (metres gained toward the goal, or along the
    shortest obstacle-free path with `along: path`; envs/rewards.py), `goal_reached`,
    `per_step`, `near_obstacle` (lidar near flag), `crash`, `out_of_workspace`. The thesis's
    ratios: closer +10..+20, goal +500..+1000, step -5..-10, near -10..-50, crash -100..-500.

    ## Starting State
    The drone hovers at its spawn point (randomised per the world file: spawn, goal, obstacle
    placement and shape), armed, in offboard mode, with zero velocity.

    ## Episode End
    Terminated: the drone is inside its goal region (`outcome` "goal"), it collided or the lidar
    crash flag is set (`"crash"`), or it left the workspace (`"out"`). Truncated: after
    `task.max_steps` steps, or `task.max_time_s` simulated seconds (`"timeout"`).

    ## Info
    `step`, `sim_time_s` (simulated time since the episode's reset began), `action`, `outcome`
    (None or goal/crash/out/timeout), `reward_terms` (name -> scaled value), `position_enu_m`,
    `command_enu_m_s` (the velocity setpoint the last action flew, ENU m/s; zero after a reset),
    `start_enu_m`, `goal_enu_m` (centre of the goal region), `distance_to_goal_m`, `crashed`,
    `near_obstacle`.

    ## Arguments
    ```python
    sitl_bridge.envs.make_env("worlds/random_goal.yaml", autopilot="direct", speed_factor=0.0,
                              seed=None, drone=0, instance_base=0, px4_bin=None)
    gymnasium.make("sitl_bridge/RandomGoal-v0", autopilot="stub")
    ```
    The keyword arguments are the fields of `sitl_bridge.envs.EnvOptions` (or pass `options=`
    whole). `autopilot`: `direct` (stub controller + physics in-process, no sockets: the fast path for
    training), `stub` (full protocol path: HIL link, stub autopilot, MAVLink, MAVSDK) or `px4`
    (real PX4 SITL from `px4_bin` / `PX4_BIN`). `speed_factor`: simulated/wall time pacing for
    `stub`/`px4` (0 = as fast as possible). `seed`: seeds the first `reset()` without a seed.
    `instance_base`: preferred first vehicle instance (ports 4560+i, 14540+i, ...): taken when
    free, else the next free block (claimed for the env's life, never shared with another run).
    `estimator`: `sensors` (default: the stub estimates its state from the simulated, noisy
    sensors, as PX4 does) or `ground_truth` (a labelled speed shortcut for `direct`/`stub`: the
    stub flies on the simulator's noise-free state, and `direct` skips the sensor simulation;
    not what PX4 sees; see `sitl_bridge.envs.ESTIMATORS`).

    ## Version History
    * v0: initial version (thesis scenarios E, ER, O, OR, W, street; backends direct/stub/px4).
    """

    metadata = {"render_modes": ["rgb_array", "rgb_array_list", "human"], "render_fps": RenderConfig().fps}

    def __init__(self, scenario: str | Path | Scenario, *, drone: int = 0, backend: Backend | None = None,
                 options: EnvOptions | None = None, **option_values: Any) -> None:
        self.options = EnvOptions.of(options, **option_values)  # autopilot=, speed_factor=, seed=, ...
        self.scenario = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
        if not 0 <= drone < self.scenario.num_drones:
            raise ValueError(f"drone must be in 0..{self.scenario.num_drones - 1}, got {drone}")
        self.drone = drone
        self.runner = EpisodeRunner.open(self.scenario, self.options, backend)
        self.backend = self.runner.backend
        self.action_space = action_space(self.scenario.task.action)  # Discrete(8) or Box(-1, 1)
        self.observation_space = observation_space(self.scenario)
        self._first_seed = self.options.seed
        self.render_mode = self.options.render_mode
        self.metadata = {**self.metadata, "render_fps": self.scenario.task.render.fps}
        self._renderer = EnvRenderer(self.scenario.world, self.scenario.task.render, self.backend,
                                     self.render_mode) if self.render_mode else None
        self._frames = FrameList(self._renderer, lambda: self.drone, lambda: self.runner.snapshot) \
            if self.render_mode == "rgb_array_list" else None
        if self._frames is not None:
            self.runner.on_frame = self._frames.capture

    def reset(self, *, seed: int | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        if seed is None and self._first_seed is not None:
            seed, self._first_seed = self._first_seed, None
        super().reset(seed=seed)
        # Each episode's layout seed comes from the env's generator: seeded runs repeat exactly.
        results = self.runner.reset(int(self.np_random.integers(2**31 - 1)))
        mine = results[self.drone]
        if self.render_mode == "human":
            self.render()
        if self._frames is not None:
            self._frames.restart()
        return mine.observation, mine.info

    def step(self, action: int | np.integer | np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self.scenario.task.action.continuous:  # the runner checks it (finite, its shape) and clips it
            results = self.runner.step({self.drone: action})
        else:
            if not self.action_space.contains(action):
                raise ValueError(f"action must be an integer in 0..{NUM_ACTIONS - 1}, got {action!r}")
            results = self.runner.step({self.drone: int(action)})
        mine = results[self.drone]
        if self.render_mode == "human":
            self.render()
        return mine.observation, mine.reward, mine.terminated, mine.truncated, mine.info

    def render(self) -> np.ndarray | None:
        """`rgb_array`: the current frame (height x width x 3, uint8; camera from the scenario's
        `task.render`); `rgb_array_list`: the frames since the last call, every 0.1 s of simulated
        time (`envs/render.FrameList`); `human`: points the GUI's camera at the drone and returns None."""
        if self._renderer is None:
            return None
        if self._frames is not None:
            return self._frames.take()
        return self._renderer.render(self.drone, self.runner.snapshot)

    def describe(self) -> str:
        """This scenario's manual (Markdown): observation table with bounds, rewards, episode end."""
        return describe(self.scenario)

    def close(self) -> None:
        self.runner.close()
