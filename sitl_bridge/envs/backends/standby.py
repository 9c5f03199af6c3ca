"""`StandbyBackend` (`EnvOptions(standby=True)`): a session backend whose next autopilots are
booted before they are needed, so an episode that cannot start in the air does not wait for
a restart (px4: ~1.2 s of wall time each, and random or learning flights crash often).

Two `SessionBackend`s run in worker processes, each with its own simulation, autopilot
processes, vehicle instances and MAVSDK clients (processes, not threads: the one booting does
not take the other's Python time): the *active* one flies the episodes; the *standby* has
booted, taken off and hovers with its lockstep held, which in lockstep freezes its autopilots
too (PX4 waits for its next sensor message and its clock stands still, so nothing of it times
out). At each reset:

1. the active one flies on into the next episode in the air where it can
   (`SessionBackend.fly_on`, ~0.1 s);
2. else the standby takes over: it flies on into the episode (the same in-air reset onto the
   new episode's layout, from its own clean hover), and the old active one restarts in the
   background as the next standby;
3. where neither can (the standby is still booting after two crashes in a row, or it is
   refused too), the active one restarts in the foreground as it would alone.

Episodes are the same as `SessionBackend`'s (the same starts, seeds and observations), so
`standby` changes speed, not results. Costs: twice the autopilot processes and instances,
and a background boot's CPU while the active one flies. Rendering and `with_simulation`
need the simulation in this process: not available with a standby.
"""

from __future__ import annotations

import logging
import socket
import subprocess
import sys
from collections.abc import Callable, Sequence
from dataclasses import replace
from multiprocessing.connection import Connection
from typing import Any, TypeVar

import numpy as np

from sitl_bridge.envs.backends.base import BackendError, Snapshot
from sitl_bridge.envs.options import EnvOptions
from sitl_bridge.world import World

T = TypeVar("T")
log = logging.getLogger(__name__)

CLOSE_TIMEOUT_S = 30.0
"""Wall seconds a worker has to close its session (stop its autopilots) before it is killed."""
KEEP_WARM_EVERY_S = 2.0
KEEP_WARM_SIM_S = 0.1
"""A waiting standby hovers `KEEP_WARM_SIM_S` of simulated time every `KEEP_WARM_EVERY_S` of
wall time: a held PX4 sends nothing, and after ~3 s without its heartbeat MAVSDK drops the
link's remote address and logs "Sending message failed" for every setpoint it streams."""


def _serve(conn: Connection, world: World, options: EnvOptions, start_altitude_m: float, takeoff: bool) -> None:
    """A worker: one `SessionBackend`, driven by (method, args) messages until "close" or
    until the parent's end of the pipe closes. Replies ("ok", result, counters) or
    ("error", message, counters). After "boot" (a restart as the standby) it keeps warm
    until the next message."""
    from sitl_bridge.envs.backends.session import SessionBackend

    backend = SessionBackend(world, options, start_altitude_m=start_altitude_m, takeoff=takeoff)
    hover = [np.zeros(3)] * backend.num_drones
    standby = False
    try:
        while True:
            try:
                if standby and not conn.poll(KEEP_WARM_EVERY_S):
                    backend.fly(hover, KEEP_WARM_SIM_S)
                    continue
                method, args = conn.recv()
            except (EOFError, OSError):
                return  # the parent is gone
            except Exception:  # noqa: BLE001 - a standby that fails to hover is booted again
                standby = False
                continue
            if method == "close":
                return
            standby = method == "boot"
            try:
                reply: tuple[Any, ...] = ("ok", backend.restart(*args) if standby else getattr(backend, method)(*args))
            except Exception as exc:  # noqa: BLE001 - every failure goes back to the parent
                standby = False
                reply = ("error", f"{type(exc).__name__}: {exc}")
            conn.send((*reply, backend.in_air_resets, backend.last_in_air_refusal))
    finally:
        backend.close()
        conn.close()


def main() -> None:
    """`python -m sitl_bridge.envs.backends.standby FD`: a worker on the inherited socket FD."""
    conn = Connection(int(sys.argv[1]))
    world, options, start_altitude_m, takeoff = conn.recv()
    _serve(conn, world, options, start_altitude_m, takeoff)


class _Worker:
    """One worker process and its socket; at most one request in flight.

    A plain subprocess, not `multiprocessing`: its spawn would re-import the user's main
    script in the worker (and fork is unsafe in a process with threads: MAVSDK, torch)."""

    def __init__(self, world: World, options: EnvOptions, start_altitude_m: float, takeoff: bool = False) -> None:
        ours, theirs = socket.socketpair()
        self.process = subprocess.Popen([sys.executable, "-m", __name__, str(theirs.fileno())],
                                        pass_fds=(theirs.fileno(),))
        theirs.close()
        self.conn = Connection(ours.detach())
        self.conn.send((world, options, start_altitude_m, takeoff))
        self.pending = False
        self.in_air_resets = 0
        self.last_in_air_refusal = ""

    def send(self, method: str, *args: Any) -> None:
        """Start `method(*args)` in the worker without waiting for it (see `result`)."""
        if self.pending:
            raise BackendError("standby worker: a request is already in flight")
        try:
            self.conn.send((method, args))
        except (OSError, ValueError) as exc:
            raise BackendError(f"standby worker exited ({exc})") from None
        self.pending = True

    def result(self) -> Any:
        """The in-flight request's result (waiting for it); BackendError where it failed."""
        try:
            status, value, self.in_air_resets, self.last_in_air_refusal = self.conn.recv()
        except (EOFError, OSError):
            raise BackendError(f"standby worker exited (exit code {self.process.poll()})") from None
        finally:
            self.pending = False
        if status == "error":
            raise BackendError(value)
        return value

    def call(self, method: str, *args: Any) -> Any:
        self.send(method, *args)
        return self.result()

    @property
    def alive(self) -> bool:
        return self.process.poll() is None

    def close(self) -> None:
        if self.alive:
            try:
                if self.pending:
                    self.result()  # a boot in flight: let it finish, then close it cleanly
                self.conn.send(("close", ()))
            except (BackendError, OSError, ValueError):
                pass
            try:
                self.process.wait(CLOSE_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.conn.close()


class StandbyBackend:
    """`SessionBackend` episodes with a standby copy booted ahead (module docstring)."""

    def __init__(self, world: World, options: EnvOptions, *, start_altitude_m: float,
                 takeoff: bool = False) -> None:
        self.name = options.autopilot
        self.num_drones = world.num_vehicles
        self.handovers = 0
        """Episodes the standby took over (each spared a restart in the foreground)."""
        self.restarts = 0
        """Episodes started by a restart in the foreground (the first included)."""
        self.last_standby_refusal = ""
        """Why the standby could not take over at the last handover it was asked for."""
        self._spec = (world, replace(options, standby=False), float(start_altitude_m), bool(takeoff))
        self._active: _Worker | None = None
        self._standby: _Worker | None = None
        self.last_in_air_refusal = ""
        """Why the active autopilots could not fly on at the last reset ('' when they did)."""
        self._flown_on = 0  # in-air resets of workers replaced since
        self._closed = False

    # -- Backend API --------------------------------------------------------------------
    def reset(self, seed: int | None = None) -> Snapshot:
        seed = 0 if seed is None else int(seed)
        if self._closed:
            raise BackendError(f"{self.name}: closed")
        if self._active is None:
            self._active, self._standby = _Worker(*self._spec), _Worker(*self._spec)
            self._standby.send("boot", seed)  # boots while the active one boots and flies
            return self._restart(seed)
        try:
            snapshot = self._active.call("fly_on", seed)
            self.last_in_air_refusal = self._active.last_in_air_refusal
        except BackendError as exc:  # its worker died: the standby takes over, or a new one starts
            snapshot, self.last_in_air_refusal = None, str(exc)
        if snapshot is not None:
            return snapshot
        snapshot = self._take_over(seed)
        return snapshot if snapshot is not None else self._restart(seed)

    def fly(self, velocities_ned_m_s: Sequence[np.ndarray], duration_s: float,
            yaws_ned_rad: Sequence[float] | None = None) -> Snapshot:
        return self._worker().call("fly", [np.asarray(v, dtype=float) for v in velocities_ned_m_s], duration_s,
                                   None if yaws_ned_rad is None else [float(y) for y in yaws_ned_rad])

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            for worker in (self._active, self._standby):
                if worker is not None:
                    worker.close()

    def with_simulation(self, use: Callable[[Any], T]) -> T:
        raise BackendError(f"{self.name}: the simulation runs in a worker process with standby=True "
                           "(rendering and with_simulation need standby=False)")

    # -- what it did ----------------------------------------------------------------------
    @property
    def in_air_resets(self) -> int:
        """Episodes started in the air: flown on by the active autopilots or, at a handover,
        by the standby's."""
        live = sum(w.in_air_resets for w in (self._active, self._standby) if w is not None)
        return self._flown_on + live

    # -- internals ------------------------------------------------------------------------
    def _worker(self) -> _Worker:
        if self._active is None:
            raise BackendError(f"{self.name}: not started (call reset())")
        return self._active

    def _take_over(self, seed: int) -> Snapshot | None:
        """The standby flies on into the episode and becomes the active one (None where it
        cannot; it then boots again in the background)."""
        standby, old = self._standby, self._active
        assert standby is not None and old is not None
        try:
            if standby.pending:
                standby.result()  # still booting: waiting costs less than a restart from scratch
            snapshot = standby.call("fly_on", seed)
            self.last_standby_refusal = standby.last_in_air_refusal
        except BackendError as exc:  # its boot failed: booted again below, the active one restarts
            snapshot, self.last_standby_refusal = None, str(exc)
        if snapshot is None:
            log.warning("%s: the standby could not take over (%s); restarting in the foreground",
                        self.name, self.last_standby_refusal)
            self._standby = self._boot(standby, seed)
            return None
        self._active, self._standby = standby, self._boot(old, seed)  # boots while this episode flies
        self.handovers += 1
        return snapshot

    def _alive(self, worker: _Worker) -> _Worker:
        """`worker`, or a new one in its place where its process has exited."""
        if worker.alive:
            return worker
        self._flown_on += worker.in_air_resets
        worker.close()
        return _Worker(*self._spec)

    def _boot(self, worker: _Worker, seed: int) -> _Worker:
        """Start `worker` (or its replacement) booting as the standby; returns it."""
        worker = self._alive(worker)
        worker.send("boot", seed)
        return worker

    def _restart(self, seed: int) -> Snapshot:
        self.restarts += 1
        self._active = self._alive(self._worker())
        return self._active.call("restart", seed)


if __name__ == "__main__":
    main()
