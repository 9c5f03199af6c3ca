"""Action names in a scenario's own action frame (the thesis's 8 actions)."""

WORLD = ("east", "west", "south", "north", "down", "up", "toward goal", "hover")
GOAL = ("right", "left", "back", "forward", "down", "up", "toward goal", "hover")
ACTION_NAMES_BY_FRAME = {"world": WORLD, "goal": GOAL}


def action_name(code: int, frame: str = "world") -> str:
    names = ACTION_NAMES_BY_FRAME[frame]
    return names[code] if 0 <= code < len(names) else str(code)


def action_code(name: str, frame: str = "world") -> int:
    names = ACTION_NAMES_BY_FRAME[frame]
    if name in names:
        return names.index(name)
    raise ValueError(f"unknown action {name!r} in the {frame} frame (expected one of {', '.join(names)})")
