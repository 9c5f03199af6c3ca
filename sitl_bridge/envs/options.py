"""`EnvOptions`: how an env runs, passed whole from `make_env` / `make_parallel_env` (or
`gymnasium.make` keyword arguments) through the env to its backend.

Adding an option is one field here (with its default and check) plus the code that reads it;
no signature in between changes.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any

from sitl_bridge.autopilot.registry import env_kind, names

ESTIMATORS = ("sensors", "ground_truth")
"""What the stub autopilot's state estimate comes from (`estimator=` of the envs):

* `sensors` (default, realistic): the stub's sensor-fusion estimator works from the simulated
  IMU, magnetometer, barometer and GPS (noise included), as PX4's EKF2 does.
* `ground_truth` (a labelled shortcut for speed, NOT what PX4 sees): the estimate is the
  simulator's noise-free state. `direct` then skips the sensor simulation and the fusion
  filter altogether; `stub` requests HIL_STATE_QUATERNION every step as PX4 does for its
  ground-truth mode (`SimSession(ground_truth_estimate=True)`), so both still agree. Not
  available with `px4` (it always runs EKF2)."""


RENDER_MODES = (None, "rgb_array", "rgb_array_list", "human")


@dataclass(frozen=True)
class EnvOptions:
    """The options of an env and its backend (see `SitlEnv`'s Arguments)."""

    autopilot: str = "direct"
    """The backend: a kind of `sitl_bridge.autopilot.registry` that envs run on
    (`direct`, `stub`, `px4`)."""
    speed_factor: float = 0.0
    """Simulated/wall time pacing of session backends (0 = as fast as possible)."""
    seed: int | None = None
    """Seeds the backend's first layout and the env's first `reset()` without a seed."""
    instance_base: int = 0
    """Preferred first vehicle instance (ports: `sitl_bridge.ports`) of session backends: taken
    when free, else the next free block; claimed for the env's life (`autopilot.allocation`)."""
    px4_bin: str | None = None
    """PX4 SITL binary (`px4`; PX4_BIN by default)."""
    gui: bool = False
    """pybullet GUI."""
    estimator: str = "sensors"
    """`sensors` or `ground_truth` (see `ESTIMATORS`)."""
    render_mode: str | None = None
    """Gymnasium render mode: None (nothing drawn, no cost), `rgb_array` (offscreen frames from
    `render()`), `human` (pybullet's GUI window; implies `gui`)."""
    standby: bool = False
    """Keep a standby copy of the session's autopilots booted and hovering, to take over where
    an episode cannot start in the air (`envs.backends.standby`; kinds that reset in the air,
    `px4`; not with rendering)."""

    def __post_init__(self) -> None:
        kind = env_kind(self.autopilot)  # ValueError naming the choices
        if self.estimator not in ESTIMATORS:
            raise ValueError(f"estimator must be one of {', '.join(ESTIMATORS)}, got {self.estimator!r}")
        if self.ground_truth and not kind.supports_ground_truth:
            able = [n for n in names(env=True) if env_kind(n).supports_ground_truth]
            raise ValueError(f"estimator='ground_truth' needs an autopilot that flies on ground truth "
                             f"({', '.join(able)}); {self.autopilot} runs its own estimator")
        if self.render_mode not in RENDER_MODES:
            raise ValueError(f"render_mode must be one of {RENDER_MODES}, got {self.render_mode!r}")
        if self.standby and not kind.resets_in_air:
            able = [n for n in names(env=True) if env_kind(n).resets_in_air]
            raise ValueError(f"standby=True needs an autopilot that flies on between episodes "
                             f"({', '.join(able)}), got {self.autopilot}")
        if self.standby and (self.uses_gui or self.render_mode is not None):
            raise ValueError("standby=True runs the simulation in worker processes: no rendering or GUI")
        if not self.speed_factor >= 0:
            raise ValueError(f"speed_factor must be >= 0, got {self.speed_factor!r}")

    @property
    def uses_gui(self) -> bool:
        """pybullet's GUI window: asked for, or `render_mode="human"`."""
        return self.gui or self.render_mode == "human"

    @property
    def ground_truth(self) -> bool:
        """The autopilots estimate from ground truth (`estimator="ground_truth"`)."""
        return self.estimator == "ground_truth"

    @property
    def first_seed(self) -> int:
        """The backend's seed before the first reset (0 without `seed`)."""
        return 0 if self.seed is None else int(self.seed)

    @classmethod
    def of(cls, options: EnvOptions | None = None, **overrides: Any) -> EnvOptions:
        """`options` (default: the defaults) with `overrides`; TypeError for an unknown name."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(overrides) - known)
        if unknown:
            raise TypeError(f"unknown env option(s) {', '.join(unknown)} (known: {', '.join(sorted(known))})")
        return replace(options or cls(), **overrides)


__all__ = ["ESTIMATORS", "RENDER_MODES", "EnvOptions"]
