"""`SimRunner`: drives a `Lockstep` from a background thread.

For callers that cannot step the simulation themselves: `sitl-bridge run` with external or
PX4 autopilots, or an environment that talks to PX4 through MAVSDK while simulated time must
keep flowing. The runner thread is the only one touching the lockstep (and through its pumps
any in-process autopilot); other threads command it:

    runner.run_for(1.0)      # exactly 1 s of simulated time, then held (blocks by default)
    runner.resume()          # run until hold()
    runner.hold()            # stop at the next step boundary; returns once held
    with runner.exclusive(): # held and not even idling: safe to reset the simulation
        sim.reset()

While held the thread keeps calling `lockstep.idle()` so in-process autopilots answer their
MAVLink API. An exception in the thread (LinkClosed, LockstepTimeout) holds the runner and is
re-raised by the next call from the controlling thread.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterator

from sitl_bridge.hil.lockstep import Lockstep

log = logging.getLogger(__name__)

_FOREVER = -1


class SimRunner:
    """Background thread running `lockstep` on command (see module docstring)."""

    def __init__(self, lockstep: Lockstep, *, idle_interval_s: float = 0.005) -> None:
        self.lockstep = lockstep
        self.idle_interval_s = idle_interval_s
        self.error: BaseException | None = None
        self._cond = threading.Condition()
        self._lock = threading.RLock()  # held by the thread while it touches the lockstep
        self._steps_left = 0  # _FOREVER: run until hold()
        self._held = True
        self._closed = False
        self._thread = threading.Thread(target=self._loop, name="sitl-bridge-sim", daemon=True)
        self._thread.start()

    # -- commands ---------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        """True while simulated time is advancing."""
        return not self._held

    def run_for(self, seconds: float, wait: bool = True, timeout_s: float | None = None) -> None:
        """Advance exactly `seconds` of simulated time, then hold. With `wait`, block until
        done (or `timeout_s` wall, then TimeoutError and the runner keeps going)."""
        steps = self.lockstep.steps_for(seconds)
        self._command(steps)
        if wait:
            self.wait(timeout_s)

    def resume(self) -> None:
        """Run until `hold()`."""
        self._command(_FOREVER)

    def hold(self, timeout_s: float | None = None) -> None:
        """Stop at the next step boundary; returns once the simulation is held."""
        self.check()
        with self._cond:
            self._steps_left = 0
            self._cond.notify_all()
        self.wait(timeout_s)

    def wait(self, timeout_s: float | None = None) -> None:
        """Block until held (a `run_for` finished, or after `hold()`)."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._held, timeout_s):
                raise TimeoutError(f"simulation still running after {timeout_s} s")
        self.check()

    @contextlib.contextmanager
    def exclusive(self, *, discard_error: bool = False) -> Iterator[Lockstep]:
        """Hold, and keep the thread off the lockstep (no idling either) inside the block.

        `discard_error`: drop the thread's error instead of raising it, for a caller that is
        about to cure it (a restart of a dead autopilot): the held thread keeps polling the
        dead link until the block starts, so a check before entering cannot be the last."""
        if not discard_error:
            self.hold()
            with self._lock:
                yield self.lockstep
            return
        with self._cond:
            self._steps_left = 0
            self._cond.notify_all()
            self._cond.wait_for(lambda: self._held)
        with self._lock:
            self.error = None  # under the lock: the thread cannot add one until the block ends
            yield self.lockstep

    def serve_until(self, until: Callable[[], bool], timeout_s: float) -> bool:
        """Held, without advancing simulated time: serve the lockstep's pumps (in-process
        autopilots' MAVLink APIs) until `until()` holds; False after `timeout_s` (wall). True at
        once when there are no pumps (nothing in-process to serve)."""
        if not self.lockstep.pumps:
            return True
        deadline = time.monotonic() + timeout_s
        while not until():
            if time.monotonic() > deadline:
                return False
            with self.exclusive() as lockstep:  # idle returns once `until()` holds, not after 1 ms
                lockstep.idle(0.001, until)
        return True

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop the thread (holding first). Idempotent."""
        with self._cond:
            self._closed = True
            self._steps_left = 0
            self._cond.notify_all()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout_s)

    def __enter__(self) -> SimRunner:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- internals ----------------------------------------------------------------------------
    def _command(self, steps: int) -> None:
        self.check()
        if self._closed:
            raise RuntimeError("SimRunner is closed")
        with self._cond:
            self._steps_left = steps
            self._held = steps == 0
            self._cond.notify_all()

    def check(self) -> None:
        """Re-raise (once) an exception that stopped the simulation thread."""
        error = self.error
        if error is not None:
            self.error = None
            raise error


    def _loop(self) -> None:
        lockstep = self.lockstep
        while True:
            with self._cond:
                if self._closed:
                    break
                if self._steps_left == 0:
                    if not self._held:
                        lockstep.hold()
                        self._held = True
                        self._cond.notify_all()
                    self._cond.wait(self.idle_interval_s)
                    idle = True
                else:
                    idle = False
            try:
                with self._lock:
                    if idle:
                        if self._steps_left == 0 and not self._closed:
                            lockstep.idle()
                        continue
                    lockstep.step()
            except BaseException as exc:  # noqa: BLE001 - handed to the controlling thread
                log.error("simulation thread stopped: %s", exc)
                with self._cond:
                    self.error = exc
                    self._steps_left = 0
                    lockstep.hold()
                    self._held = True
                    self._cond.notify_all()
                continue
            with self._cond:
                if self._steps_left > 0:
                    self._steps_left -= 1
        lockstep.hold()
        with self._cond:
            self._held = True
            self._cond.notify_all()
