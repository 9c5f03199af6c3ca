"""After each lockstep step, wait until a real PX4 has finished the work that step woke.

Lockstep hands PX4 the sensors of simulated time t and waits for its HIL_ACTUATOR_CONTROLS
answer to t. That answer comes from the rate controller; the rest of what the new time woke
(estimator, position and attitude control, navigator, commander, MAVLink streams) runs on in
PX4's threads in wall time. On an idle machine it is done long before the next sensor message;
on a busy one a thread may still be waiting for a core when the next message moves PX4's
clock, and then computes with other inputs than on another run (measured: about one boot in
ten under load ended its take-off 0.2-1.75 m off in height).

So after each step the lockstep looks at PX4's threads (the scheduler state in
/proc/<pid>/task/<tid>/stat) and goes on once none is runnable ('R'). PX4's threads only work
when woken (a new simulated time, a uORB publication, a datagram), and a thread wakes the next
one before it sleeps itself, so while work of the step is left at least one of them is
runnable. Threads that wait in wall time (the MAVLink receivers polling their sockets) count
too: what they handle (a setpoint) belongs before the next step as well. The wait is bounded
(`MAX_WAIT_S`): a PX4 not done by then is late as it was before; a stopped PX4 ('T') counts
as asleep, so a frozen one does not slow every step. Before PX4 answers its first step (while
it boots, in wall time) nothing is waited for.

The stat files are kept open and re-read with `pread` (a fresh read of procfs each time): an
open and a close per thread and step would cost more than the check itself.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Iterable
from dataclasses import dataclass

from sitl_bridge.autopilot.px4.delivery import POLL_S, thread_file, thread_ids

MAX_WAIT_S = 0.05
"""Wall seconds at most one step waits for PX4's threads to sleep."""
RESCAN_EVERY = 250
"""Looks (about one per step) between two listings of a process's threads (PX4 starts a
thread now and then after boot, e.g. for a parameter save)."""


@dataclass
class QuiescenceStats:
    """Counters since construction."""

    waits: int = 0
    """Calls that found PX4 with work left at the first look."""
    capped: int = 0
    """Calls that gave up after `MAX_WAIT_S` with a thread still runnable."""
    wait_s: float = 0.0
    """Wall seconds spent waiting."""


class Px4Quiescence:
    """Watches the threads of PX4 processes (by pid) for runnable ones (see module docstring)."""

    def __init__(self, max_wait_s: float = MAX_WAIT_S) -> None:
        self.max_wait_s = max_wait_s
        self.stats = QuiescenceStats()
        self._files: dict[int, dict[str, int]] = {}  # pid -> thread id -> open stat file
        self._looks: dict[int, int] = {}

    def busy(self, pid: int) -> bool:
        """True while a thread of process `pid` is runnable (False once it is gone)."""
        looks = self._looks.get(pid, 0)
        if pid not in self._files or looks % RESCAN_EVERY == 0:
            self._scan(pid)
        self._looks[pid] = looks + 1
        files = self._files[pid]
        for tid, fd in list(files.items()):
            try:
                stat = os.pread(fd, 512, 0)
            except OSError:
                stat = b""
            if not stat:  # the thread ended
                os.close(files.pop(tid))
                continue
            # "tid (name) S ...": the name may hold spaces and parentheses, the state follows the last ')'
            if stat[stat.rindex(b")") + 2] == ord("R"):
                return True
        return False

    def wait(self, pids: Iterable[int]) -> bool:
        """Return once no thread of any of `pids` is runnable (True), or after `max_wait_s`
        of wall time (False)."""
        pids = list(pids)
        if not any(self.busy(pid) for pid in pids):
            return True
        start = time.monotonic()
        self.stats.waits += 1
        try:
            while any(self.busy(pid) for pid in pids):
                if time.monotonic() - start > self.max_wait_s:
                    self.stats.capped += 1
                    return False
                time.sleep(POLL_S)  # a poll of procfs: it leaves the core to PX4, times no flight
            return True
        finally:
            self.stats.wait_s += time.monotonic() - start

    def forget(self, keep: Iterable[int] = ()) -> None:
        """Close the files of every process but `keep` (e.g. after PX4 was stopped)."""
        keep = set(keep)
        for pid in [p for p in self._files if p not in keep]:
            for fd in self._files.pop(pid).values():
                os.close(fd)
            self._looks.pop(pid, None)

    def _scan(self, pid: int) -> None:
        files = self._files.setdefault(pid, {})
        for tid in thread_ids(pid):
            if tid not in files:
                with contextlib.suppress(OSError):
                    files[tid] = os.open(thread_file(pid, tid, "stat"), os.O_RDONLY)

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            self.forget()


__all__ = ["MAX_WAIT_S", "Px4Quiescence", "QuiescenceStats"]
