"""`sitl-bridge run --restart-autopilot`: a dead (SIGKILL) or frozen (SIGSTOP) autopilot is
restarted and the simulation goes on. Real processes, loopback only; the
PX4 variants need PX4_BIN. Also: a SIGKILLed owner's temp PX4 run dir is removed later."""

from __future__ import annotations

import os
import queue
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from sitl_bridge.autopilot.allocation import claim_free_instances
from sitl_bridge.autopilot.px4.temp_dirs import (
    OWNER_FILE,
    PREFIX,
    make_temp_run_dir,
    remove_stale_run_dirs,
)
from sitl_bridge.ports import PX4_LAST_OWN_API_INSTANCE

FREEZE_S = 6.0
"""Longer than the lockstep's 5 s actuator timeout: the stopped autopilot is declared frozen."""


def _free_px4_instance() -> int:
    """A PX4 instance in 0..9 free now, for a child `sitl-bridge run --instance-base N`, which
    claims exactly it (a lock cannot be handed on; a run that took it meanwhile makes the
    child fail with InstancesBusy, never share it)."""
    # from a random start: another run picking at the same moment likely takes another one
    first = random.randint(0, PX4_LAST_OWN_API_INSTANCE)
    with claim_free_instances(1, first=first, last=PX4_LAST_OWN_API_INSTANCE) as claim:
        return claim.base


def _children(pid: int) -> list[int]:
    try:
        return [int(p) for p in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def _descendants(pid: int) -> list[int]:
    found = []
    for child in _children(pid):
        found += [child, *_descendants(child)]
    return found


def _autopilot_pid(run_pid: int, marker: str, old: int | None = None, timeout_s: float = 60.0) -> int:
    """The pid of the autopilot process (`marker` in its command line) under `run`."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for pid in _descendants(run_pid):
            try:
                cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
            except OSError:
                continue
            if marker in cmdline and pid != old:
                return pid
        time.sleep(0.1)
    raise AssertionError(f"no autopilot process ({marker}) under sitl-bridge run")


class _Lines:
    """The merged output of a process, line by line, read in a thread."""

    def __init__(self, process: subprocess.Popen) -> None:
        self.all: list[str] = []
        self._queue: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._read, args=(process,), daemon=True).start()

    def _read(self, process: subprocess.Popen) -> None:
        for line in process.stdout:
            self._queue.put(line)

    def wait_for(self, text: str, timeout_s: float, *, at_start: bool = False) -> str:
        """The first line containing `text` (`at_start`: beginning with it)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                line = self._queue.get(timeout=0.2)
            except queue.Empty:
                continue
            self.all.append(line)
            if line.startswith(text) if at_start else text in line:
                return line
        raise AssertionError(f"{text!r} not printed within {timeout_s} s:\n{''.join(self.all)}")

    def everything(self) -> str:
        """All the output read so far, also what no `wait_for` took yet."""
        while not self._queue.empty():
            self.all.append(self._queue.get())
        return "".join(self.all)


def _kill_and_freeze(extra: list[str], marker: str, instance: int, boot_s: float) -> None:
    run = subprocess.Popen(
        [sys.executable, "-m", "sitl_bridge", "run", "--restart-autopilot", "--instance-base", str(instance),
         "--speed-factor", "1", *extra],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines = _Lines(run)
    try:
        lines.wait_for("t=", boot_s + 15, at_start=True)  # a status line: started and simulating
        try:
            first = _autopilot_pid(run.pid, marker)
        except AssertionError as exc:
            raise AssertionError(f"{exc} (run's exit status {run.poll()}); its output:\n{lines.everything()}") from None
        time.sleep(1.0)
        os.kill(first, signal.SIGKILL)
        restart = lines.wait_for("restarting it (restart 1)", 30)
        assert "dead" in restart and "console.log" not in restart
        lines.wait_for("ready again", boot_s)
        second = _autopilot_pid(run.pid, marker, old=first)
        time.sleep(2.0)  # answering the lockstep (a link only waits for an autopilot that has)
        os.kill(second, signal.SIGSTOP)
        time.sleep(FREEZE_S)
        os.kill(second, signal.SIGCONT)
        assert "frozen" in lines.wait_for("restarting it (restart 2)", 30)
        lines.wait_for("ready again", boot_s)
        time.sleep(1.0)
        assert run.poll() is None, "".join(lines.all)  # still simulating
        run.send_signal(signal.SIGINT)
        assert run.wait(30) == 130
    finally:
        if run.poll() is None:
            run.kill()
            run.wait(10)


def test_run_restarts_a_killed_and_a_frozen_stub_process(free_instance: int) -> None:
    _kill_and_freeze(["--stub-process"], "sitl_bridge stub", free_instance, boot_s=60)


def test_without_the_flag_a_killed_stub_process_ends_run(free_instance: int) -> None:
    run = subprocess.Popen(
        [sys.executable, "-m", "sitl_bridge", "run", "--stub-process", "--instance-base", str(free_instance)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines = _Lines(run)
    try:
        lines.wait_for("t=", 60, at_start=True)
        os.kill(_autopilot_pid(run.pid, "sitl_bridge stub"), signal.SIGKILL)
        assert run.wait(30) == 1
    finally:
        if run.poll() is None:
            run.kill()
            run.wait(10)


def test_run_restarts_a_killed_and_a_frozen_px4(px4_bin: str) -> None:
    _kill_and_freeze(["--autopilot", "px4", "--px4-bin", px4_bin], "bin/px4", _free_px4_instance(), boot_s=120)


def test_a_killed_owners_temp_run_dir_is_removed_by_the_next(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", None)
    owner = subprocess.Popen([sys.executable, "-c",
                              "from sitl_bridge.autopilot.px4.temp_dirs import make_temp_run_dir as m; "
                              "print(m(), flush=True); import time; time.sleep(60)"],
                             stdout=subprocess.PIPE, text=True)
    stale = Path(owner.stdout.readline().strip())
    assert stale.parent == tmp_path and stale.name.startswith(PREFIX) and (stale / OWNER_FILE).is_file()
    assert remove_stale_run_dirs() == []  # its owner still runs
    owner.kill()  # what SIGKILL of `sitl-bridge run` does
    owner.wait(10)
    foreign = tmp_path / (PREFIX + "not-ours")  # no owner file: never touched
    foreign.mkdir()
    mine = make_temp_run_dir()
    assert not stale.exists() and foreign.is_dir() and mine.is_dir()


def test_sigkill_of_run_with_px4_leaves_no_temp_dir_after_the_next_start(px4_bin: str) -> None:
    import tempfile

    instance = _free_px4_instance()
    run = subprocess.Popen(
        [sys.executable, "-m", "sitl_bridge", "run", "--autopilot", "px4", "--px4-bin", px4_bin,
         "--instance-base", str(instance)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines = _Lines(run)
    try:
        lines.wait_for("t=", 120, at_start=True)
        owned = [p for p in Path(tempfile.gettempdir()).glob(PREFIX + "*")
                 if (p / OWNER_FILE).is_file() and (p / OWNER_FILE).read_text().split()[0] == str(run.pid)]
        assert len(owned) == 1
        run.kill()
        run.wait(10)
        time.sleep(1.0)  # PX4 dies with its parent (parent-death signal)
    finally:
        if run.poll() is None:
            run.kill()
    assert owned[0].exists()
    remove_stale_run_dirs()  # what the next `run` does first
    assert not owned[0].exists()
