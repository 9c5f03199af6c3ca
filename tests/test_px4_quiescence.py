"""`autopilot/px4/quiescence.py` on real processes: a sleeping process is quiet at once, a
spinning one is waited for until the bound, a stopped one (a frozen PX4) counts as asleep, and
a thread that finishes its work is seen going to sleep."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from sitl_bridge.autopilot.px4.quiescence import Px4Quiescence

pytestmark = pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="reads Linux procfs")


def _child(code: str) -> subprocess.Popen:
    child = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert child.stdout is not None and child.stdout.readline() == "up\n"
    return child


def _stop(child: subprocess.Popen) -> None:
    child.kill()
    child.wait()


def test_a_sleeping_process_is_quiet_at_once() -> None:
    child = _child("import time; print('up', flush=True); time.sleep(60)")
    try:
        quiet = Px4Quiescence(max_wait_s=30.0)  # on a busy machine it may wait for a core to get to sleep
        assert quiet.wait([child.pid])
        waits = quiet.stats.waits
        assert quiet.wait([child.pid]) and quiet.wait([child.pid])
        assert quiet.stats.waits == waits and quiet.stats.capped == 0  # found asleep at the first look
    finally:
        _stop(child)


def test_a_spinning_thread_is_waited_for_until_the_bound_and_a_stopped_one_not() -> None:
    child = _child("import threading\nthreading.Thread(target=lambda: [0 for _ in iter(int, 1)]).start()\n"
                   "print('up', flush=True)\nimport time; time.sleep(60)")
    try:
        quiet = Px4Quiescence(max_wait_s=0.05)
        started = time.monotonic()
        assert not quiet.wait([child.pid])
        assert time.monotonic() - started >= 0.05
        assert quiet.stats.capped == 1
        child.send_signal(signal.SIGSTOP)
        deadline = time.monotonic() + 10.0  # the stop takes effect once the child is scheduled
        while any(stat.read_text().rsplit(")", 1)[1].split()[0] != "T"
                  for stat in Path(f"/proc/{child.pid}/task").glob("*/stat")):  # every thread stopped
            assert time.monotonic() < deadline
            time.sleep(0.01)
        assert quiet.wait([child.pid])
    finally:
        _stop(child)


def test_a_thread_that_finishes_its_work_is_seen_asleep() -> None:
    """The worker wakes on a pipe (runnable before the write returns), spins 0.1 s, sleeps."""
    child = subprocess.Popen(
        [sys.executable, "-c", "import sys, time\nprint('up', flush=True)\nsys.stdin.readline()\n"
         "end = time.monotonic() + 0.1\nwhile time.monotonic() < end: pass\ntime.sleep(60)"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline() == "up\n"
        quiet = Px4Quiescence(max_wait_s=30.0)
        assert quiet.wait([child.pid])  # asleep in readline
        waits = quiet.stats.waits
        started = time.monotonic()  # before the write: the child's 0.1 s start after it
        child.stdin.write("go\n")
        child.stdin.flush()
        assert quiet.wait([child.pid])
        assert time.monotonic() - started >= 0.1
        assert quiet.stats.waits == waits + 1 and quiet.stats.capped == 0
    finally:
        _stop(child)
    assert not quiet.busy(child.pid)  # gone: nothing left to wait for
    quiet.forget()
