"""Action names in a scenario's own action frame (the thesis's 8 actions), and actions as logs keep them."""

from typing import Any

import numpy as np

WORLD = ("east", "west", "south", "north", "down", "up", "toward goal", "hover")
GOAL = ("right", "left", "back", "forward", "down", "up", "toward goal", "hover")
ACTION_NAMES_BY_FRAME = {"world": WORLD, "goal": GOAL}


def action_name(code: int, frame: str = "world") -> str:
    """The name of action `code` in `frame` (`world` or `goal`); unknown codes as their number."""
    names = ACTION_NAMES_BY_FRAME[frame]
    return names[code] if 0 <= code < len(names) else str(code)


def action_code(name: str, frame: str = "world") -> int:
    """The code of the action called `name` in `frame` (ValueError listing the valid names)."""
    names = ACTION_NAMES_BY_FRAME[frame]
    if name not in names:
        raise ValueError(f"unknown action {name!r} in the {frame} frame (expected one of {', '.join(names)})")
    return names.index(name)


def logged_action(action: Any) -> int | list[float]:
    """An action as episode logs and traces keep it: a discrete code as an int, a continuous
    command (a Box vector) as its float32 components, 9 significant digits each (what reads
    back as the same float32: a logged episode flies again exactly)."""
    if isinstance(action, (int, np.integer)):
        return int(action)
    return [float(f"{v:.9g}") for v in np.asarray(action, dtype=np.float32).reshape(-1)]
