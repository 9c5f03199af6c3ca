"""How a greedy episode flew, beyond its outcome: simulated time, path length and how much the
commanded velocity changed, per drone-episode (what "continuous control flies shorter, smoother
paths" is measured with).

- `time_s`: simulated seconds from the reset to the drone's last step (its own end);
- `path_m`: length of the polyline through the drone's positions after the reset and after each
  decision (a chord per decision: at 1 s decisions it can cut a curve short that 0.1 s decisions
  sample, so it is a lower bound, tighter at the faster rate);
- `command_change_m_s2`: the summed change of the commanded velocity between consecutive
  decisions (|v_k - v_(k-1)|, ENU m/s; the first command is not counted, whatever the drone did
  before it) divided by `time_s`: 0 for a flight at one constant command, large for a zig-zag.

A value the env did not report (no `sim_time_s`, no positions, no `command_enu_m_s`) is None.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from sitl_bridge.rl.evaluation.rollout import Trace


def episode_measures(trace: Trace) -> dict[str, Any]:
    """One drone-episode as JSON: `episode`, `drone`, `outcome`, `steps`, `time_s`, `path_m`,
    `command_change_m_s2` (module docstring)."""
    times = trace.sim_times_s
    time_s = times[-1] - times[0] if len(times) >= 2 else None
    positions = np.asarray(trace.positions_enu_m, dtype=float)
    path_m = float(np.linalg.norm(np.diff(positions, axis=0), axis=1).sum()) if len(positions) >= 1 else None
    commands = np.asarray(trace.commands_enu_m_s, dtype=float)
    change = None
    if len(commands) == trace.steps and time_s is not None and time_s > 0.0:
        total = float(np.linalg.norm(np.diff(commands, axis=0), axis=1).sum()) if len(commands) >= 2 else 0.0
        change = total / time_s
    return {"episode": trace.episode, "drone": trace.drone, "outcome": trace.outcome, "steps": trace.steps,
            "time_s": _rounded(time_s), "path_m": _rounded(path_m), "command_change_m_s2": _rounded(change)}


def _rounded(value: float | None) -> float | None:
    """Millimetre / millisecond resolution: enough for a mean, and a small cache file."""
    return None if value is None or not math.isfinite(value) else round(value, 4)
