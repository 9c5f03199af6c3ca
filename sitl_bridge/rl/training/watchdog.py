"""`sitl-bridge train --watchdog`: run training in a child process and bring it back when it dies
or freezes.

The child is `sitl-bridge train ...` in its own process group. It is restarted with `--resume
RUN_DIR` (from its newest good checkpoint) when it exits abnormally (crash, kill -9) or when its
heartbeat (rl/training/heartbeat.py) makes no progress for `freeze_timeout_s` (frozen learner, simulator
or link). Teardown kills the whole process group, so no simulator/autopilot child is left.
Restarts are logged to RUN_DIR/watchdog.jsonl; more than `max_restarts_per_hour` stops it.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

from sitl_bridge.rl.common.atomic import append_durably
from sitl_bridge.rl.training.heartbeat import read_heartbeat

WATCHDOG_LOG = "watchdog.jsonl"
RUN_DIR_PREFIX = "run directory: "


@dataclass
class WatchdogReport:
    """What the watchdog did: the final exit code, the restarts and why."""

    exit_code: int
    run_dir: Path | None
    restarts: list[dict] = field(default_factory=list)
    gave_up: str | None = None


class Watchdog:
    """Supervise one training run given as the `train` command's arguments (without --watchdog)."""

    def __init__(self, train_argv: list[str], freeze_timeout_s: float = 120.0, max_restarts_per_hour: int = 10,
                 poll_s: float = 0.5) -> None:
        self.train_argv = list(train_argv)
        self.freeze_timeout_s = freeze_timeout_s
        self.max_restarts_per_hour = max_restarts_per_hour
        self.poll_s = poll_s
        self.run_dir: Path | None = None
        self._restart_times: deque[float] = deque()
        self._child: subprocess.Popen | None = None

    # -- one child -----------------------------------------------------------------------
    def _spawn(self, argv: list[str]) -> subprocess.Popen:
        cmd = [sys.executable, "-m", "sitl_bridge", "train", *argv]
        child = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True, start_new_session=True)
        threading.Thread(target=self._relay_stderr, args=(child,), daemon=True).start()
        return child

    def _relay_stderr(self, child: subprocess.Popen) -> None:
        # Pass the child's messages on and learn its run directory from its first line.
        assert child.stderr is not None
        for line in child.stderr:
            sys.stderr.write(line)
            if self.run_dir is None and line.startswith(RUN_DIR_PREFIX):
                self.run_dir = Path(line[len(RUN_DIR_PREFIX):].split(" (resuming")[0].strip())

    def _teardown(self, child: subprocess.Popen) -> None:
        """Kill the child's whole process group (simulator, autopilot, learner)."""
        for sig in (signal.SIGCONT, signal.SIGKILL):  # SIGCONT: a stopped group still dies cleanly
            try:
                os.killpg(child.pid, sig)
            except ProcessLookupError:
                break
        child.wait()

    def _watch(self, child: subprocess.Popen) -> str | None:
        """Wait for the child: None when it finished cleanly, otherwise why it must restart."""
        last_beat: tuple | None = None
        last_progress = time.monotonic()
        startup_s = max(4 * self.freeze_timeout_s, 300.0)  # imports + simulator start come before the first beat
        while True:
            code = child.poll()
            if code is not None:
                return None if code == 0 else (f"exit code {code}" if code > 0 else f"killed by signal {-code}")
            beat = read_heartbeat(self.run_dir) if self.run_dir is not None else None
            # Only this child's beats count: the last one of a killed child is no sign of life.
            key = None if beat is None or beat.get("pid") != child.pid else (beat.get("episode"), beat.get("wall_time"))
            if key != last_beat:
                last_beat, last_progress = key, time.monotonic()
            elif time.monotonic() - last_progress > (self.freeze_timeout_s if key else startup_s):
                return (f"no heartbeat progress for {self.freeze_timeout_s:g} s (frozen)" if key
                        else f"no heartbeat within {startup_s:g} s of starting (frozen start)")
            time.sleep(self.poll_s)  # polling pace

    # -- the loop ------------------------------------------------------------------------
    def run(self) -> WatchdogReport:
        """Supervise until training finishes, is refused, or restarts too often. SIGTERM ends the
        watchdog like Ctrl-C: the child's process group is torn down first."""
        signal.signal(signal.SIGTERM, _raise_keyboard_interrupt)
        report = WatchdogReport(exit_code=0, run_dir=None)
        argv = self.train_argv
        while True:
            child = self._child = self._spawn(argv)
            try:
                reason = self._watch(child)
            finally:
                self._teardown(child)
            report.run_dir = self.run_dir
            if reason is None:
                return report
            if child.returncode == 2 and reason == "exit code 2":  # a usage/config error: restarting cannot help
                report.exit_code, report.gave_up = 2, "the training command was refused (see its error above)"
                return report
            if self.run_dir is None:
                report.exit_code, report.gave_up = 1, f"training failed ({reason}) before it made a run directory"
                return report
            now = time.monotonic()
            self._restart_times.append(now)
            while self._restart_times and now - self._restart_times[0] > 3600:
                self._restart_times.popleft()
            entry = {"time": time.time(), "reason": reason, "heartbeat": read_heartbeat(self.run_dir),
                     "restart": len(report.restarts) + 1}
            if len(self._restart_times) > self.max_restarts_per_hour:
                entry["gave_up"] = True
                report.exit_code = 1
                report.gave_up = (f"{len(self._restart_times) - 1} restarts in the last hour reached "
                                  f"--max-restarts-per-hour {self.max_restarts_per_hour}; last failure: {reason}")
                self._log(entry)
                return report
            report.restarts.append(entry)
            self._log(entry)
            print(f"watchdog: training {reason}; restart {entry['restart']} from the last checkpoint",
                  file=sys.stderr)
            argv = _resume_argv(self.train_argv, self.run_dir)

    def _log(self, entry: dict) -> None:
        assert self.run_dir is not None
        append_durably(self.run_dir / WATCHDOG_LOG, (json.dumps(entry) + "\n").encode())


def _resume_argv(train_argv: list[str], run_dir: Path) -> list[str]:
    """`--resume RUN_DIR` plus the options a resume accepts (--episodes, --no-progress)."""
    keep: list[str] = []
    i = 0
    while i < len(train_argv):
        arg = train_argv[i]
        name = arg.split("=", 1)[0]
        takes_value = "=" not in arg and i + 1 < len(train_argv) and not train_argv[i + 1].startswith("--")
        if name == "--episodes":
            keep += train_argv[i:i + 2] if takes_value else [arg]
        elif name == "--no-progress":
            keep.append(arg)
        i += 2 if (takes_value and name.startswith("--") and name != "--no-progress") else 1
    return ["--resume", str(run_dir), *keep]


def _raise_keyboard_interrupt(_signum: int, _frame: object) -> None:
    raise KeyboardInterrupt
