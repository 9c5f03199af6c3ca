"""Where the shipped data lives: the scenario files (`worlds/`) and the PX4 parameter
overrides (`px4_params/`).

Looked for in order: an environment override (`SITL_BRIDGE_WORLDS`, `SITL_BRIDGE_PX4_PARAMS`),
the source tree next to the package (a checkout or an editable install), then the data folder
of a regular install (`<prefix>/share/sitl-bridge/`, see `[tool.setuptools.data-files]`).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

SOURCE_ROOT = Path(__file__).resolve().parent.parent
INSTALLED_DATA = Path(sys.prefix) / "share" / "sitl-bridge"


def _existing(env_var: str, folder: str) -> list[Path]:
    override = os.environ.get(env_var)
    candidates = [Path(override)] if override else []
    candidates += [SOURCE_ROOT / folder, INSTALLED_DATA / folder]
    return [path for path in candidates if path.is_dir()]


def worlds_dirs() -> list[Path]:
    """Every folder that holds world files, most specific first (the current directory's
    `worlds/` last)."""
    dirs = _existing("SITL_BRIDGE_WORLDS", "worlds")
    local = Path.cwd() / "worlds"
    return dirs + ([local] if local.is_dir() and local.resolve() not in {d.resolve() for d in dirs} else [])


def worlds_dir() -> Path:
    """The folder of the shipped scenarios (where registered env ids find their files)."""
    dirs = _existing("SITL_BRIDGE_WORLDS", "worlds")
    return dirs[0] if dirs else SOURCE_ROOT / "worlds"


def px4_params_dir() -> Path:
    """The folder of the shipped `*.params` overrides for PX4 and the stub."""
    dirs = _existing("SITL_BRIDGE_PX4_PARAMS", "px4_params")
    return dirs[0] if dirs else SOURCE_ROOT / "px4_params"
