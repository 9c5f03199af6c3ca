"""Compiled per-step kernels (numba), cached on disk and invalidated by every source they use.

The per-physics-step math (rotor model, state read, IMU synthesis, the stub's estimator, control
cascade and mixer) runs as numba-compiled kernels; the classes that own each component call
them, so there is one implementation for the HIL path, the stub process and the in-process
`direct` backend alike.

* `dual`: a plain Python function that kernels may call too (`numba.extending.register_jitable`):
  Python callers pay nothing, kernels compile the same source inline.
* `kernel(*uses)`: `numba.njit(cache=True)`, except that the on-disk cache is also keyed on the
  source files of everything the kernel calls into (`uses`: modules, or other kernels, whose
  own sources count transitively). numba itself checks only the kernel's own file, so an edit of
  a helper in another module would otherwise leave a stale compiled kernel behind.

A cold cache compiles each kernel on its first call (seconds, once per source change); a warm one
loads it in milliseconds.
"""

from __future__ import annotations

import hashlib
import inspect
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any, TypeVar

from numba import njit
from numba.extending import register_jitable

from sitl_bridge import compile_notice

F = TypeVar("F", bound=Callable[..., Any])

__all__ = ["dual", "kernel"]
compile_notice.install()  # a cold cache says so before it compiles for minutes


def dual(fn: F) -> F:
    """`fn` unchanged for Python callers, and compilable into kernels (same source)."""
    return register_jitable(fn)


def _sources_of(used: ModuleType | Callable[..., Any]) -> frozenset[str]:
    known = getattr(used, "sitl_sources", None)
    if known is not None:
        return known
    if isinstance(used, ModuleType):
        return frozenset({str(Path(used.__file__ or "").resolve())})
    return frozenset({str(Path(inspect.getsourcefile(used) or "").resolve())})


def kernel(*uses: ModuleType | Callable[..., Any]) -> Callable[[F], F]:
    """Decorator: a cached numba kernel whose cache also depends on the sources of `uses`."""

    def wrap(fn: F) -> F:
        try:
            dispatcher = njit(cache=True)(fn)
        except RuntimeError:  # no writable cache location (read-only install): compile per process
            dispatcher = njit(cache=False)(fn)
            dispatcher.sitl_sources = _sources_of(fn)
            return dispatcher  # type: ignore[return-value]
        sources = frozenset({str(Path(sys.modules[fn.__module__].__file__ or "").resolve())})
        for used in uses:
            sources |= _sources_of(used)
        digest = hashlib.sha256()
        for path in sorted(sources):
            digest.update(Path(path).read_bytes())
        try:
            # numba compares this stamp with the one stored in the cache index (its own file's
            # hash); folding in the other sources makes an edit of any of them a cache miss
            cache_file = dispatcher._cache._cache_file
            cache_file._source_stamp = (cache_file._source_stamp, digest.hexdigest())
        except AttributeError:  # numba internals changed: compile every time rather than go stale
            dispatcher = njit(cache=False)(fn)
        dispatcher.sitl_sources = sources
        return dispatcher  # type: ignore[return-value]

    return wrap
