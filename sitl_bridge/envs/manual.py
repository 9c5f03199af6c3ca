"""A scenario's manual in Markdown, generated from its file: what the learner sees and earns."""

from __future__ import annotations

import numpy as np

from sitl_bridge.client.actions import NUM_ACTIONS
from sitl_bridge.envs.features import FEATURE_MEANINGS
from sitl_bridge.envs.rewards import PER_SECOND
from sitl_bridge.envs.scenario import Scenario, load_scenario
from sitl_bridge.envs.task import ActionConfig

ACTION_MEANINGS = {
    "world": ("east", "west", "south", "north", "down", "up", "toward the goal", "hover"),
    "goal": ("right (of the start-goal direction)", "left", "back (away from the goal)",
             "forward (toward the goal's side)", "down", "up", "toward the goal", "hover"),
}
"""Action codes 0-7 in each action frame (`envs/actions.py` applies them)."""


def _bounds(values: np.ndarray) -> str:
    if np.all(values == values[0]):
        return f"{float(values[0]):g}"
    if values.size <= 6:
        return "[" + ", ".join(f"{float(v):g}" for v in values) + "]"
    return f"{float(np.min(values)):g} .. {float(np.max(values)):g}"


VELOCITY_AXES = {
    "world": ("east", "north", "up"),
    "goal": ("right of the start-goal direction", "forward (along it, horizontally)", "up"),
    "body": ("right of the drone's heading", "forward (the nose, horizontally)", "up"),
}
"""Axes of a continuous velocity action in each frame (`envs/actions.py` applies them)."""


def _actions(a: ActionConfig) -> list[str]:
    """The `## Actions` section: the discrete table, or the continuous vector's components."""
    if not a.continuous:
        lines = [
            "## Actions",
            f"Discrete({NUM_ACTIONS}), each a velocity of {a.speed_m_s:g} m/s held for {a.duration_s:g} s of "
            "simulated time" + (f" then {a.zero_velocity_s:g} s hover" if a.zero_velocity_s else "")
            + f", frame `{a.frame}`" + (f"; for drones {list(a.swap_drones)} 0/1 and 2/3 are swapped"
                                         if a.swap_drones else ""),
            "",
            "| action | meaning |",
            "|---|---|",
        ]
        return lines + [f"| {code} | {meaning} |" for code, meaning in enumerate(ACTION_MEANINGS[a.frame])]
    lines = [
        "## Actions",
        f"Box(-1, 1, ({a.size},), float32): a velocity setpoint held for {a.duration_s:g} s of simulated time "
        f"(one decision every {a.duration_s:g} s), frame `{a.frame}`. The vector (x, y, z) times "
        f"{a.max_speed_m_s:g} m/s is the velocity, its norm capped at 1 (so the speed never exceeds "
        f"{a.max_speed_m_s:g} m/s in any direction); components are clipped to [-1, 1] first, and NaN or "
        "inf is an error.",
        "",
        "| index | meaning | at 1 |",
        "|---|---|---|",
    ]
    lines += [f"| {i} | velocity {axis} | {a.max_speed_m_s:g} m/s |" for i, axis in enumerate(VELOCITY_AXES[a.frame])]
    if a.yaw == "rate":
        lines.append(f"| 3 | yaw rate, counter-clockwise seen from above (left) | {a.max_yaw_rate_deg_s:g} deg/s |")
    else:
        lines += ["", "The heading is held (`yaw: hold`)."]
    return lines


def describe(scenario: Scenario) -> str:
    """Markdown: description, action settings, observation table, rewards, episode end."""
    task = scenario.task
    world = scenario.world
    lines = [f"# {world.name}", "", world.description.strip() or "(no description)", ""]
    if world.encounter is not None:
        lines += ["## Encounters", *world.encounter.describe(), ""]
    lines += _actions(task.action)
    lines += [
        "",
        f"## Observation (per drone, {task.observation_size} values, float32)",
        "| index | feature | size | values | unit | low | high |",
        "|---|---|---|---|---|---|---|",
    ]
    index = 0
    for f in task.observation:
        meaning, unit = FEATURE_MEANINGS.get(f.name, ("", ""))
        lines.append(f"| {index}..{index + f.size - 1} | `{f.name}` | {f.size} | {meaning} | {unit} | "
                     f"{_bounds(f.low)} | {_bounds(f.high)} |")
        index += f.size
    lines += ["", "## Rewards", "| term | scale |", "|---|---|"]
    lines += [f"| `{t.name}` | {t.scale:g}" + (" per second" if t.name in PER_SECOND else "") + " |"
              for t in task.rewards]
    step_s = task.action.step_s
    if step_s != 1.0 and any(t.name in PER_SECOND for t in task.rewards):
        lines.append(f"\nThe terms per second pay scale x {step_s:g} each {step_s:g} s step "
                     "(the same return for the same flight at any decision rate).")
    lines += [f"\n`{t.name}` measures progress along the shortest path to the goal box around the static "
              f"obstacles, kept {t.path.clearance_m:g} m clear, on a {t.path.cell_m:g} m grid "
              "(not along the straight line)." for t in task.rewards if t.path is not None]
    end = task.end
    ends = ["goal region reached"]
    ends.append("collision" + (" or lidar crash flag" if end.crash_on_lidar else ""))
    if end.crash_on_ground:
        ends.append(f"ground contact below {end.ground_contact_m:g} m outside the goal (crash)")
    if end.out_of_workspace:
        ends.append("left the workspace")
    if any(f.name in ("own_priority", "other_priority") for f in task.observation):
        lines += ["", "## Priority", f"Rule `{task.priority}` (sitl_bridge/envs/priority.py): "
                  "1 = right of way, 0 = yields."]
    lines += ["", "## Episode end",
              f"Terminated: {'; '.join(ends)}. Truncated: after {task.max_steps} steps"
              + (f" ({task.max_time_s:g} s of simulated time)." if task.max_time_s is not None else ".")]
    if world.num_vehicles > 1:
        after = "lands if it is at its goal, else hovers" if end.after_goal == "land" else "hovers"
        blame = ("the drones without right of way (one with right of way over all in it stops, truncated "
                 "and uncharged)" if end.conflict_blame == "give_way" else "every drone in it")
        lines.append(f"A drone whose episode ended {after} while the others fly on. A crash between "
                     f"drones (centres within {end.conflict_m:g} m) is charged to {blame}.")
        if end.min_separation_m > 0.0:
            lines.append(f"A flying drone closer than {end.min_separation_m:g} m to another drone still "
                         "in the air loses separation: a crash between drones, charged the same way.")
    lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """`python -m sitl_bridge.envs [FILE...]`: print the manual of each scenario file
    (default: every file of the worlds directory)."""
    import sys

    from sitl_bridge.envs import worlds_dir
    from sitl_bridge.errors import ConfigError

    paths = (argv if argv is not None else sys.argv[1:]) or sorted(str(p) for p in worlds_dir().glob("*.yaml"))
    for path in paths:
        try:
            print(describe(load_scenario(path)))
        except ConfigError as exc:
            print(exc, file=sys.stderr)
            return 1
    return 0
