"""Child processes that end with their parent.

A sweep worker or a PX4 process left running after its parent was killed keeps training or
holding ports with nobody to read its results. Linux's parent-death signal makes the kernel kill
such a child; elsewhere nothing is done (children there are only cleaned up by a normal exit).
"""

from __future__ import annotations

import ctypes
import signal
from typing import Any

try:  # loaded at import, not in a forked child (no imports or locks between fork and exec)
    _LIBC: Any = ctypes.CDLL(None, use_errno=True)
except OSError:  # pragma: no cover - not Linux
    _LIBC = None
_PR_SET_PDEATHSIG = 1


def die_with_parent() -> None:
    """Ask the kernel to SIGKILL this process when the thread that started it ends.

    Call it in the child (a `preexec_fn`, or a process pool's initializer). It fires when the
    starting *thread* ends, so start children from a thread that lives as long as they should."""
    if _LIBC is not None and hasattr(_LIBC, "prctl"):
        _LIBC.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
