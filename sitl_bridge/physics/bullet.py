"""pybullet, imported once without its build-time banner.

pybullet's C extension prints "pybullet build time: ..." on stderr when first imported; that
line would break the one-line error contract of the CLI (`worlds check`). Modules of
sitl-bridge import pybullet as `from sitl_bridge.physics.bullet import p`.
"""

from __future__ import annotations

import os
import sys
from types import ModuleType


def _import_quietly() -> ModuleType:
    try:
        fd = sys.__stderr__.fileno() if sys.__stderr__ is not None else -1
    except (OSError, ValueError):
        fd = -1
    if fd < 0 or "pybullet" in sys.modules:
        import pybullet
        return pybullet
    sys.__stderr__.flush()
    saved = os.dup(fd)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, fd)
        import pybullet
    finally:
        os.dup2(saved, fd)
        os.close(saved)
        os.close(devnull)
    return pybullet


p = _import_quietly()

__all__ = ["p"]
