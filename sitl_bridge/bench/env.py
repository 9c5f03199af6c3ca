"""`sitl-bridge bench --env`: env steps per second, real-time factor and reset time per backend.

Flies the obstacle scenario (one drone, 35 + 6 + 6 lidar rays in every observation) with a
seeded random policy for `--seconds` of simulated time per configuration, resetting whenever
an episode ends. Configurations (`CONFIGS`): `direct` with the default `sensors` estimator
(the stub fuses the simulated sensors, as PX4 does), `direct` with the labelled
`ground_truth` estimator (no sensor simulation or fusion; the speed option), then `stub` on
free vehicle instances (full protocol path, `sensors`). It prints per configuration:

* steps/s: env steps per wall second (each step = 1 s of simulated flight by default);
* real-time factor: simulated seconds flown in steps per wall second spent in `step()`, and
  per CPU second of this process (all its threads: the in-process stub and MAVSDK's
  included; the figure to compare on a busy machine, the target is >= 150x for
  `direct`);
* reset: wall seconds per `reset()` (mean and max) and CPU seconds of this process per reset
  (mean), the in-place episode start included; at least MIN_RESETS of them (extra resets after
  the flight when episodes were too long).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sitl_bridge.bench.stub import BENCH_INSTANCE_BASE
from sitl_bridge.envs import make_env, worlds_dir

SCENARIO = "obstacle.yaml"
CONFIGS = (("direct", "sensors"), ("direct", "ground_truth"), ("stub", "sensors"))
"""(backend, estimator) pairs measured, in order."""
BACKENDS = tuple(dict.fromkeys(backend for backend, _ in CONFIGS))
MIN_RESETS = 5


@dataclass
class EnvFigures:
    """What one backend achieved."""

    backend: str
    steps: int
    step_wall_s: float
    step_cpu_s: float
    sim_s: float
    resets: list[float]
    reset_cpu_s: list[float] = field(default_factory=list)
    estimator: str = "sensors"

    @property
    def steps_per_s(self) -> float:
        return self.steps / self.step_wall_s if self.step_wall_s > 0 else 0.0

    @property
    def real_time_factor(self) -> float:
        return self.sim_s / self.step_wall_s if self.step_wall_s > 0 else 0.0

    @property
    def real_time_factor_cpu(self) -> float:
        return self.sim_s / self.step_cpu_s if self.step_cpu_s > 0 else 0.0

    @property
    def label(self) -> str:
        """`direct`, `direct/ground_truth`, `stub`, ... (the estimator when not the default)."""
        return self.backend if self.estimator == "sensors" else f"{self.backend}/{self.estimator}"

    def line(self) -> str:
        return (f"{self.label:>19}: {self.steps_per_s:7.1f} env steps/s, real-time factor "
                f"{self.real_time_factor:6.1f}x wall ({self.real_time_factor_cpu:.1f}x per CPU s), "
                f"reset {np.mean(self.resets):.3f} s mean / "
                f"{np.max(self.resets):.3f} s max wall, {np.mean(self.reset_cpu_s):.3f} s CPU "
                f"({len(self.resets)} resets, {self.steps} steps)")


def measure(backend: str, scenario: Path, seconds: float, seed: int = 0,
            estimator: str = "sensors") -> EnvFigures:
    """Fly `seconds` of simulated time of random actions on `backend` with `estimator`."""
    # session backends claim a free instance from here up (px4: in 0..9)
    env = make_env(scenario, autopilot=backend, speed_factor=0.0, seed=seed, instance_base=BENCH_INSTANCE_BASE,
                   estimator=estimator)
    rng = np.random.default_rng(seed)
    step_s = env.scenario.task.action.step_s
    figures = EnvFigures(backend, 0, 0.0, 0.0, 0.0, [], estimator=estimator)
    try:
        env.reset(seed=seed)  # first start builds everything; not a reset figure
        while figures.sim_s < seconds:
            t0, c0 = time.perf_counter(), time.process_time()
            _, _, terminated, truncated, _ = env.step(int(rng.integers(8)))
            figures.step_wall_s += time.perf_counter() - t0
            figures.step_cpu_s += time.process_time() - c0
            figures.steps += 1
            figures.sim_s += step_s
            if terminated or truncated:
                _timed_reset(env, figures)
        while len(figures.resets) < MIN_RESETS:
            _timed_reset(env, figures)
    finally:
        env.close()
    return figures


def _timed_reset(env, figures: EnvFigures) -> None:
    t0, c0 = time.perf_counter(), time.process_time()
    env.reset()
    figures.resets.append(time.perf_counter() - t0)
    figures.reset_cpu_s.append(time.process_time() - c0)


def run(args: argparse.Namespace) -> int:
    """Print the figures of every configuration that can run here."""
    seconds = float(getattr(args, "seconds", 20.0))
    scenario = worlds_dir() / SCENARIO
    print(f"env benchmark: {SCENARIO}, random actions, {seconds:g} s simulated per configuration")
    status = 0
    for backend, estimator in CONFIGS:
        label = backend if estimator == "sensors" else f"{backend}/{estimator}"
        try:
            print(measure(backend, scenario, seconds, estimator=estimator).line(), flush=True)
        except ImportError as exc:
            print(f"{label:>19}: unavailable ({exc})")
        except Exception as exc:  # a failing backend is a result to report, not a crash
            print(f"{label:>19}: FAILED: {type(exc).__name__}: {exc}")
            status = 1
    return status
