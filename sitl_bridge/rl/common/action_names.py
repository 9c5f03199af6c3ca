"""Action names in a scenario's own action frame (the thesis's 8 actions)."""

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
