"""Thread-CPU timers patched onto live objects' methods, for the step profilers in tools/."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any


@contextmanager
def timed_methods(objects: dict[str, Any], timed: Sequence[tuple[str, str, str, str]],
                  clock: Callable[[], int] = time.thread_time_ns) -> Iterator[tuple[dict[str, int], dict[str, int]]]:
    """Wrap each `(name, parent, object key, method)` of `timed` on its instance with an
    accumulator of `clock` ns (inclusive); yields (totals, calls) by name. Objects that are
    missing (None) or lack the method are skipped. The class's methods come back on exit."""
    totals = {name: 0 for name, *_ in timed}
    calls = {name: 0 for name, *_ in timed}
    patched = []
    for name, _parent, path, method in timed:
        obj = objects.get(path)
        if obj is None or not hasattr(obj, method):
            continue
        original = getattr(obj, method)

        def timer(*args: Any, _f: Callable[..., Any] = original, _n: str = name, **kwargs: Any) -> Any:
            t0 = clock()
            try:
                return _f(*args, **kwargs)
            finally:
                totals[_n] += clock() - t0
                calls[_n] += 1

        setattr(obj, method, timer)
        patched.append((obj, method))
    try:
        yield totals, calls
    finally:
        for obj, method in patched:
            delattr(obj, method)  # back to the class's method
