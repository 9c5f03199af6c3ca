"""Vehicle instance numbers for runs in parallel: claimed with lock files, never shared.

Instance i means the ports 4560+i, 14580+i, ... (`sitl_bridge.ports`) and, with real PX4,
`px4 -i i`, so two runs on one machine must never use the same instance, whatever their kind.
A claim is an exclusive `flock` on `/tmp/sitl-bridge-instance-N.lock`, held by an open file
for as long as the instance is in use: the kernel drops it when the holder exits, even by
SIGKILL, so a crashed run never blocks an instance.

The pick is the claim: `claim_free_instances` returns the instances it found already locked,
and whoever runs on them adopts that held claim (`SimSession(instance_base=claim)`) instead
of checking once and claiming again later, so two runs starting at the same moment can never
pick the same instances. A search also skips instances that something taking no claim uses:
bound ports (a `sitl-bridge stub` started by hand, a MAVSDK client) or a PX4 server running as
one (`/tmp/px4_lock-N`, e.g. started by hand for the `external` kind).

Searches take turns (`SEARCH_LOCK_NAME`): a search locks a block's instances one by one and lets
them go when a later one is taken, so two searches at once each saw the other's passing locks
as claims and skipped free blocks they never came back to. Two searchers one instance apart
leapfrogged like that through a whole range (each holding the first instance of its next block
while the other took the second) and one fell off its end with free instances left behind.

Handing instances to a child process: hand nothing (or a preferred first instance) and let
the child claim its own. A lock cannot be handed on: the child's `flock` on a file of its own
conflicts with the parent's, and a parent that released first leaves a gap another run can
take.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path

from sitl_bridge.autopilot.fleet import SessionError
from sitl_bridge.autopilot.px4.process import px4_server_running
from sitl_bridge.ports import MAX_INSTANCE, instance_free

LOCK_DIR = Path("/tmp")
"""Fixed, not `$TMPDIR`: ports are one per machine, so their claims must be too (two runs with
different TMPDIRs would not see each other's lock files). PX4 keeps its own in /tmp too."""
LOCK_NAME = "sitl-bridge-instance-{}.lock"
SEARCH_LOCK_NAME = "sitl-bridge-instance-search.lock"
"""Held (`flock`) by `claim_free_instances` for its whole search: one search at a time per machine."""
SEARCH_WAIT_S = 10.0
"""How long a search waits for its turn before it searches anyway (a holder that never lets go,
e.g. a stopped process: its claims stay exclusive, only the pick may skip a block)."""


class InstancesBusy(SessionError):
    """The instances asked for are claimed by another run or used by something else."""


def lock_path(instance: int) -> Path:
    """The lock file whose exclusive `flock` claims vehicle instance `instance`."""
    return LOCK_DIR / LOCK_NAME.format(instance)


class InstanceClaim:
    """Held claims of consecutive vehicle instances; `release()`, the end of a `with` block or
    the holder's exit frees them."""

    def __init__(self, instances: Iterable[int], fds: Iterable[int]) -> None:
        self.instances = tuple(instances)
        self._fds = list(fds)
        self._owner_pid = os.getpid()
        self.held = True
        """True until `release()`."""

    @property
    def base(self) -> int:
        """The first instance."""
        return self.instances[0]

    def release(self) -> None:
        """Free the instances. Idempotent."""
        for fd in self._fds:
            # The owner unlocks first, so that a forked child sharing the open file does not
            # keep the claim alive; such a child's copy only closes its own fd.
            if os.getpid() == self._owner_pid:
                with contextlib.suppress(OSError):
                    fcntl.flock(fd, fcntl.LOCK_UN)
            with contextlib.suppress(OSError):
                os.close(fd)
        self._fds.clear()
        self.held = False

    def __enter__(self) -> InstanceClaim:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    def __del__(self) -> None:
        # An owner dropped without release() (an env never closed) frees its instances now,
        # not only at exit; at interpreter shutdown the modules may be gone: the kernel frees.
        with contextlib.suppress(Exception):
            self.release()

    def __repr__(self) -> str:
        return f"InstanceClaim({list(self.instances)}, held={self.held})"


def _lock(instance: int, check_free: bool) -> int | None:
    """The fd holding `instance`'s lock, or None when it is claimed (or, with `check_free`,
    used by something that takes no claim)."""
    try:
        fd = os.open(lock_path(instance), os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
    except PermissionError:  # another user's lock file we may not open: treat as theirs
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return None
    # Checked while holding the lock: no other claimer can be between its check and its lock.
    if check_free and (px4_server_running(instance) or not instance_free(instance)):
        os.close(fd)
        return None
    with contextlib.suppress(OSError):  # who holds it, for a person looking (not read by us)
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
    return fd


def claim_instances(instances: Iterable[int], *, check_free: bool = False) -> InstanceClaim:
    """Claim exactly these instances, or raise InstancesBusy naming the first one claimed by
    another run. `check_free`: also refuse one whose ports are bound or as which a PX4 server
    runs (a search does; a session given its instances leaves that to binding them, since a
    user's MAVSDK may already listen on the client port)."""
    instances = tuple(instances)
    fds: list[int] = []
    for instance in instances:
        fd = _lock(instance, check_free)
        if fd is None:
            InstanceClaim(instances, fds).release()
            raise InstancesBusy(f"vehicle instance {instance} is in use by another run "
                                f"({lock_path(instance)} is locked, or its ports or a PX4 server are); "
                                f"choose another --instance-base")
        fds.append(fd)
    return InstanceClaim(instances, fds)


@contextlib.contextmanager
def _search_turn(wait_s: float = SEARCH_WAIT_S) -> Iterator[None]:
    """Hold the machine's search lock for the block (waiting up to `wait_s` for it); without it
    (not there in time, or its file not usable) the search runs anyway."""
    try:
        fd = os.open(LOCK_DIR / SEARCH_LOCK_NAME, os.O_RDONLY | os.O_CREAT | os.O_CLOEXEC, 0o666)
    except OSError:
        yield
        return
    try:
        deadline = time.monotonic() + wait_s
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except OSError:
                if time.monotonic() >= deadline:
                    break
                time.sleep(0.001)
        yield
    finally:
        os.close(fd)  # drops the lock if held


def claim_free_instances(count: int, first: int = 0, last: int = MAX_INSTANCE) -> InstanceClaim:
    """Claim `count` consecutive free instances (a run's vehicles are consecutive) within
    0..`last`: the first free block from `first` upward, else from 0 (`first` is a preference:
    an env's `instance_base`). Raises InstancesBusy when none is free. One search at a time per
    machine (`SEARCH_LOCK_NAME`), so a lock met on the way is a claim, not another search's
    passing try."""
    top = last - count + 1  # the highest first instance that fits
    bases = [*range(max(first, 0), top + 1), *range(0, min(first, top + 1))]
    with _search_turn():
        for base in bases:
            with contextlib.suppress(InstancesBusy):
                return claim_instances(range(base, base + count), check_free=True)
    raise InstancesBusy(f"no {count} consecutive free vehicle instances in 0..{last}: too many runs in parallel")


def hold_instances(instances: Sequence[int], adopted: InstanceClaim | None = None) -> Callable[[], None]:
    """For a run on `instances` (a session): adopt the claim its caller picked and holds
    (checked: still held, exactly these instances; the caller releases it), or claim them
    now. Returns what the run calls when done: the release of its own claim, else nothing."""
    if adopted is None:
        return claim_instances(instances).release
    if not adopted.held or adopted.instances != tuple(instances):
        raise InstancesBusy(f"{adopted!r} does not hold the instances {list(instances)} the run needs")
    return lambda: None


__all__ = ["LOCK_DIR", "SEARCH_LOCK_NAME", "InstanceClaim", "InstancesBusy", "claim_free_instances", "claim_instances",
           "hold_instances", "lock_path"]
