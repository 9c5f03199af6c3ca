"""PX4 parameter overrides: the `px4_params/*.params` files (`NAME VALUE [wall [MAX]]`, see
px4_params/offboard.params) and how `wall` timeouts scale with the speed factor."""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from sitl_bridge.data_paths import px4_params_dir
from sitl_bridge.errors import ConfigError

# Speed factor assumed for `wall` timeouts when F = 0 ("as fast as possible").
MAX_SPEED_ASSUMED = 30.0
PARAMS_DIR = px4_params_dir()


@dataclass(frozen=True)
class Px4Param:
    """One override line: `NAME VALUE [wall [MAX]]` (see px4_params/offboard.params)."""

    name: str
    value: float | int
    wall: bool = False
    maximum: float | None = None

    def resolved(self, speed_factor: float) -> float | int:
        """The value PX4 gets: wall-clock timeouts scaled by the effective speed factor."""
        if not self.wall:
            return self.value
        factor = speed_factor if speed_factor > 0 else MAX_SPEED_ASSUMED
        value = float(self.value) * factor
        return min(value, self.maximum) if self.maximum is not None else value


_NAME = re.compile(r"^[A-Z][A-Z0-9_]{0,15}$")


def _number(text: str) -> float | int:
    return int(text) if re.fullmatch(r"[-+]?\d+", text) else float(text)


def read_params(path: str | os.PathLike[str]) -> list[Px4Param]:
    """Parse a `.params` override file; a bad line is a ConfigError naming file and line."""
    source = str(path)
    try:
        lines = Path(path).read_text().splitlines()
    except OSError as exc:
        raise ConfigError(f"{source}: cannot read file ({exc.strerror})") from None
    params = []
    for number, raw in enumerate(lines, start=1):
        fields = raw.split("#", 1)[0].split()
        if not fields:
            continue
        where = f"{source}: line {number}"
        if not _NAME.match(fields[0]):
            raise ConfigError(f"{where}: expected a PX4 parameter name, got {fields[0]!r}")
        try:
            value = _number(fields[1]) if len(fields) > 1 else None
            maximum = float(fields[3]) if len(fields) > 3 else None
        except ValueError:
            value = None
        wall = len(fields) > 2 and fields[2] == "wall"
        if value is None or len(fields) > 4 or (len(fields) > 2 and not wall):
            raise ConfigError(f"{where}: expected `NAME VALUE [wall [MAX]]`, got {raw.strip()!r}")
        params.append(Px4Param(fields[0], value, wall, maximum))
    return params


def load_param_overrides(
    params_dir: str | os.PathLike[str] | None = None,
    extra: Mapping[str, float | int] | None = None,
) -> dict[str, Px4Param]:
    """All overrides of `params_dir/*.params` (name order, later wins) plus `extra`."""
    directory = Path(params_dir) if params_dir else PARAMS_DIR
    files = sorted(directory.glob("*.params"))
    if not files:
        # Never start PX4 silently without its offboard/failsafe overrides.
        raise ConfigError(f"{directory}: no *.params files (PX4 parameter overrides) found")
    merged: dict[str, Px4Param] = {}
    for path in files:
        for param in read_params(path):
            merged[param.name] = param
    for name, value in (extra or {}).items():
        merged[name] = Px4Param(name, value)
    return merged


def format_value(value: float) -> str:
    """A parameter value as PX4's `param set` reads it."""
    return str(value) if isinstance(value, int) else f"{value:.6g}"
