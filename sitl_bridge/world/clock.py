"""Simulated seconds as physics steps: the one conversion.

Every span of simulated time (an action, a hold, `run_for`, `sitl-bridge run --duration`, a
backend's poll interval) becomes a whole number of physics steps here, by one rule: seconds
are rounded to whole microseconds, then divided by the world's `physics.step_us`. Spans that
must be exact (actions, `run_for`) raise when they are not a whole number of steps; the world
loader refuses a `physics.step_us` that does not divide the task's action and hold spans, so
every backend flies the same steps. Polls and timeouts may round to the nearest step.
"""

from __future__ import annotations

from sitl_bridge.world.schema import PhysicsSettings

DEFAULT_STEP_US: int = PhysicsSettings.step_us
"""The physics step of a world that does not set `physics.step_us` (PX4's 250 Hz lockstep)."""


def seconds_to_us(seconds: float) -> int:
    """`seconds` as whole microseconds (the simulated clock's unit)."""
    return round(seconds * 1_000_000)


def divides(step_us: int, seconds: float) -> bool:
    """True when `seconds` is a whole number of `step_us` steps."""
    return seconds_to_us(seconds) % step_us == 0


def whole_steps(seconds: float, step_us: int, *, exact: bool = True) -> int:
    """The number of `step_us` physics steps in `seconds` (>= 0).

    exact: ValueError unless `seconds` is a whole number of steps (spans that must be exact);
    False: the nearest whole number (polls, timeouts, a `--duration`)."""
    total_us = seconds_to_us(seconds)
    if total_us < 0:
        if exact:
            raise ValueError(f"{seconds} s is not a whole number of {step_us} us steps")
        return 0
    steps, remainder = divmod(total_us, step_us)
    if remainder:
        if exact:
            raise ValueError(f"{seconds} s is not a whole number of {step_us} us steps")
        if 2 * remainder >= step_us:
            steps += 1
    return steps


def nearest_whole_steps_s(seconds: float, step_us: int) -> float:
    """`seconds` rounded to the nearest whole number of steps, in seconds (a poll interval
    or a `--duration` that `run_for` then takes exactly)."""
    return whole_steps(seconds, step_us, exact=False) * step_us / 1e6


__all__ = ["DEFAULT_STEP_US", "divides", "nearest_whole_steps_s", "seconds_to_us", "whole_steps"]
