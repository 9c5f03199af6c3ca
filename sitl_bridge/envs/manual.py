"""A scenario's manual in Markdown, generated from its file: what the learner sees and earns."""

from __future__ import annotations

import numpy as np

from sitl_bridge.envs.scenario import Scenario


def _bounds(values: np.ndarray) -> str:
    lo, hi = float(np.min(values)), float(np.max(values))
    return f"{lo:g}" if lo == hi else f"{lo:g} .. {hi:g}"


def describe(scenario: Scenario) -> str:
    """Markdown: description, action settings, observation table, rewards, episode end."""
    task = scenario.task
    world = scenario.world
    lines = [f"# {world.name}", "", world.description.strip() or "(no description)", ""]
    a = task.action
    lines += [
        "## Actions",
        f"Discrete(8), {a.speed_m_s:g} m/s for {a.duration_s:g} s"
        + (f" then {a.zero_velocity_s:g} s hover" if a.zero_velocity_s else "")
        + f", frame `{a.frame}`" + (f", swapped for drones {list(a.swap_drones)}" if a.swap_drones else ""),
        "",
        f"## Observation (per drone, {task.observation_size} values, float32)",
        "| index | feature | size | low | high |",
        "|---|---|---|---|---|",
    ]
    index = 0
    for f in task.observation:
        lines.append(f"| {index}..{index + f.size - 1} | `{f.name}` | {f.size} | "
                     f"{_bounds(f.low)} | {_bounds(f.high)} |")
        index += f.size
    lines += ["", "## Rewards", "| term | scale |", "|---|---|"]
    lines += [f"| `{t.name}` | {t.scale:g} |" for t in task.rewards]
    end = task.end
    ends = ["goal region reached"]
    ends.append("collision" + (" or lidar crash flag" if end.crash_on_lidar else ""))
    if end.out_of_workspace:
        ends.append("left the workspace")
    lines += ["", "## Episode end",
              f"Terminated: {'; '.join(ends)}. Truncated: after {task.max_steps} steps.", ""]
    return "\n".join(lines)
