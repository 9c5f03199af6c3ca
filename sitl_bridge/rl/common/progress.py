"""Progress of long work (training, evaluation, rule extraction): a tqdm bar on a terminal, plain
periodic lines otherwise, so a log file gets a line every `interval_s`, not a status twice a second."""

from __future__ import annotations

import sys
import time
from typing import Any, TextIO

PLAIN_INTERVAL_S = 15.0
"""Seconds between two plain progress lines when the output is not a terminal."""


class Progress:
    """Counts `total` units of work; `update(n, key=value...)` after each, `close()` at the end."""

    def __init__(self, total: int, desc: str, *, unit: str = "ep", enabled: bool = True, initial: int = 0,
                 stream: TextIO | None = None, interval_s: float = PLAIN_INTERVAL_S) -> None:
        self.total, self.desc, self.unit, self.count = total, desc, unit, initial
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.interval_s = interval_s
        self.postfix: dict[str, Any] = {}
        self._start = time.monotonic()
        self._last_line = self._start
        self._bar = None
        if enabled and self.stream.isatty():
            from tqdm import tqdm

            self._bar = tqdm(total=total, initial=initial, desc=desc, unit=unit, dynamic_ncols=True,
                             file=self.stream)
        elif enabled:
            self._line("started")

    def update(self, n: int = 1, **postfix: Any) -> None:
        """`n` more units done; `postfix` values are shown next to the count."""
        self.count += n
        self.postfix.update(postfix)
        if self._bar is not None:
            self._bar.update(n)
            if postfix:
                self._bar.set_postfix(self.postfix, refresh=False)
        elif self.enabled and time.monotonic() - self._last_line >= self.interval_s:
            self._line()

    def close(self) -> None:
        """End the bar, or print the final plain line."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        elif self.enabled:
            self._line("done")
        self.enabled = False

    def _line(self, note: str = "") -> None:
        elapsed = time.monotonic() - self._start
        fields = " ".join(f"{k}={v}" for k, v in self.postfix.items())
        print(f"{self.desc}: {self.count}/{self.total} {self.unit} in {elapsed:.0f} s {fields} {note}".rstrip(),
              file=self.stream, flush=True)
        self._last_line = time.monotonic()

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
