"""One stderr line when numba really compiles a kernel of `sitl_bridge.jit` (a cold cache).

A first run after installing, or after an edit of a kernel's sources, compiles the per-step
kernels (a minute or more on a slow, loaded machine) before anything else is printed; without a
word the program looks hung. numba fires `numba:compile` only on a cache miss, so a warm run
loads its kernels and prints nothing.
"""

from __future__ import annotations

import sys

from numba.core import event

NOTICE = ("compiling the simulator's numba kernels (once after installing or editing them; "
          "can take a minute or two, later runs load them from the cache)")


class _FirstCompileNotice(event.Listener):
    """Prints `NOTICE` at the first compilation of one of our kernels in this process."""

    def __init__(self) -> None:
        self.said = False

    def on_start(self, ev: event.Event) -> None:
        dispatcher = (ev.data or {}).get("dispatcher")
        if self.said or not hasattr(dispatcher, "sitl_sources"):
            return  # said once per process; someone else's numba code is not ours to announce
        self.said = True
        print(NOTICE, file=sys.stderr, flush=True)

    def on_end(self, ev: event.Event) -> None:
        pass


_listener: _FirstCompileNotice | None = None


def install() -> None:
    """Install the listener (once per process)."""
    global _listener
    if _listener is None:
        _listener = _FirstCompileNotice()
        event.register("numba:compile", _listener)
