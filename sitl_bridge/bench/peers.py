"""Other pybullet drone simulators measured beside ours in the same bench run, when installed.

Each peer flies one quadrotor in its own standard set-up for `sim_s` simulated seconds per
repetition, resets included, and gives a real-time factor (simulated s per wall s) that
`bench.suite` turns into a fraction of the bare pybullet loop measured next to it:

* `gym_pybullet_drones`: `CtrlAviary` (one Crazyflie 2.x, 240 Hz physics, control at every
  physics step) flown to a hover point by `DSLPIDControl`, its PID example's loop.
* `pyflyt`: `PyFlyt/QuadX-Waypoints` (newest registered version) with random actions, 30 Hz
  agent steps.

Neither is a dependency of this project: a peer that does not import is reported as skipped
(`{"skipped": ...}`), never installed by the bench.
"""

from __future__ import annotations

import importlib.util
import inspect
import time
from collections.abc import Callable
from typing import Any

import numpy as np

PEERS = {"gym_pybullet_drones": "gym_pybullet_drones", "pyflyt": "PyFlyt"}
"""Bench key -> the module that must import for it to be measured."""


def missing(key: str) -> str | None:
    """Why the peer `key` cannot be measured here (None when its package is installed)."""
    module = PEERS[key]
    if importlib.util.find_spec(module) is None:
        return f"{module} not installed (pip install {module.replace('_', '-')} to measure it)"
    return None


def _fly_for(step: Callable[[], float], sim_s: float) -> float:
    """Real-time factor of calling `step` (returns the simulated s it flew) for `sim_s` simulated s."""
    flown, start = 0.0, time.perf_counter()
    while flown < sim_s:
        flown += step()
    return flown / (time.perf_counter() - start)


def gym_pybullet_drones_rtfs(sim_s: float, warmup_s: float, reps: int) -> tuple[list[float], dict[str, Any]]:
    """Real-time factors of `CtrlAviary` + `DSLPIDControl` (one per repetition) and what was flown."""
    from gym_pybullet_drones.control.DSLPIDControl import DSLPIDControl
    from gym_pybullet_drones.envs.CtrlAviary import CtrlAviary
    from gym_pybullet_drones.utils.enums import DroneModel, Physics

    if "pyb_freq" not in inspect.signature(CtrlAviary).parameters:
        raise RuntimeError("gym_pybullet_drones: a pre-Gymnasium version (no pyb_freq): not supported")
    env = CtrlAviary(drone_model=DroneModel.CF2X, num_drones=1, physics=Physics.PYB, pyb_freq=240,
                     ctrl_freq=240, gui=False, record=False)
    control = DSLPIDControl(drone_model=DroneModel.CF2X)
    target = np.array([0.0, 0.0, 1.0])
    step_s = float(env.CTRL_TIMESTEP)
    try:
        obs, _ = env.reset(seed=0)
        action = np.zeros((1, 4))
        episode_steps = int(10.0 / step_s)  # a fresh episode every 10 simulated s: resets counted
        count = [0]

        def step() -> float:
            nonlocal obs
            obs, _, _, _, _ = env.step(action)
            action[0, :], _, _ = control.computeControlFromState(
                control_timestep=step_s, state=obs[0], target_pos=target, target_rpy=np.zeros(3))
            count[0] += 1
            if count[0] % episode_steps == 0:
                obs, _ = env.reset()
                control.reset()
            return step_s

        _fly_for(step, warmup_s)
        rtfs = [_fly_for(step, sim_s) for _ in range(reps)]
    finally:
        env.close()
    return rtfs, {"setup": "CtrlAviary cf2x + DSLPIDControl to a hover point, 240 Hz physics and control",
                  "step_s": step_s}


def pyflyt_rtfs(sim_s: float, warmup_s: float, reps: int) -> tuple[list[float], dict[str, Any]]:
    """Real-time factors of PyFlyt's QuadX-Waypoints with random actions (one per repetition)."""
    import gymnasium
    import PyFlyt.gym_envs  # noqa: F401 - registers the PyFlyt/ environments

    ids = sorted((i for i in gymnasium.registry if i.startswith("PyFlyt/QuadX-Waypoints-v")),
                 key=lambda i: int(i.rsplit("-v", 1)[1]))
    if not ids:
        raise RuntimeError("PyFlyt: no PyFlyt/QuadX-Waypoints environment registered")
    agent_hz = 30
    env = gymnasium.make(ids[-1], agent_hz=agent_hz)
    step_s = 1.0 / agent_hz
    try:
        env.reset(seed=0)
        env.action_space.seed(0)

        def step() -> float:
            _, _, terminated, truncated, _ = env.step(env.action_space.sample())
            if terminated or truncated:
                env.reset()
            return step_s

        _fly_for(step, warmup_s)
        rtfs = [_fly_for(step, sim_s) for _ in range(reps)]
    finally:
        env.close()
    return rtfs, {"setup": f"{ids[-1]}, random actions, {agent_hz} Hz agent steps", "step_s": step_s}


MEASURE = {"gym_pybullet_drones": gym_pybullet_drones_rtfs, "pyflyt": pyflyt_rtfs}
