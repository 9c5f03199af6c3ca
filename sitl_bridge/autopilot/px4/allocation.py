"""PX4 instance numbers for runs in parallel: claimed with lock files, never shared.

PX4 SITL instances 0..9 each have their own MAVLink API port (above 9 they share one, see
`sitl_bridge.ports`), so parallel PX4-backed envs and runs draw from 0..9. A claim is an
exclusive `flock` on `$TMPDIR/sitl-bridge-px4-instance-N.lock`, held by an open file for as
long as the instance is in use: the kernel drops it when the holder exits, even by SIGKILL, so
a crashed run never blocks an instance. An instance is only claimed when its ports are free
and no PX4 server runs as it (one started by hand, `/tmp/px4_lock-N`).
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import IO

from sitl_bridge.autopilot.px4.process import Px4Error, px4_server_running
from sitl_bridge.ports import PX4_LAST_OWN_API_INSTANCE, instance_free

LOCK_NAME = "sitl-bridge-px4-instance-{}.lock"


def _lock_path(instance: int) -> Path:
    return Path(tempfile.gettempdir()) / LOCK_NAME.format(instance)


class InstanceClaim:
    """Held lock files of some PX4 instances (release() or process exit frees them)."""

    def __init__(self, instances: Sequence[int], files: Sequence[IO[bytes]]) -> None:
        self.instances = tuple(instances)
        self._files = list(files)

    def release(self) -> None:
        """Free the instances. Idempotent."""
        for handle in self._files:
            with contextlib.suppress(OSError):
                handle.close()
        self._files.clear()


def _try_lock(instance: int, ports_free: bool) -> IO[bytes] | None:
    handle = _lock_path(instance).open("ab")
    try:
        fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        handle.close()
        return None
    if px4_server_running(instance) or (ports_free and not instance_free(instance)):
        handle.close()  # in use by something that takes no claim (a PX4 or a run by hand)
        return None
    handle.truncate(0)
    handle.write(f"{os.getpid()}\n".encode())
    handle.flush()
    return handle


def claim_instances(instances: Sequence[int], *, ports_free: bool = False) -> InstanceClaim:
    """Claim exactly these instances, or raise Px4Error naming the busy one. `ports_free`:
    their ports must be free too (not when the claimer already opened its HIL links)."""
    files = []
    for instance in instances:
        handle = _try_lock(instance, ports_free)
        if handle is None:
            InstanceClaim(instances, files).release()
            raise Px4Error(f"PX4 instance {instance} is in use by another run or PX4 (its ports or "
                           f"{_lock_path(instance)}); choose another --instance-base")
        files.append(handle)
    return InstanceClaim(instances, files)


def claim_free_instances(count: int, first: int = 0, last: int = PX4_LAST_OWN_API_INSTANCE) -> InstanceClaim:
    """Claim `count` consecutive free instances in first..last (a vehicle's instances are
    consecutive), or raise Px4Error when none are free."""
    for base in range(first, last - count + 2):
        with contextlib.suppress(Px4Error):
            return claim_instances(range(base, base + count), ports_free=True)
    raise Px4Error(f"no {count} consecutive free PX4 instances in {first}..{last}: "
                   f"too many PX4 runs in parallel")


def free_px4_instances(count: int) -> tuple[int, ...]:
    """`count` consecutive instances free now (claimed and released at once: for handing to a
    child process, which claims them itself)."""
    claim = claim_free_instances(count)
    claim.release()
    return claim.instances


@contextlib.contextmanager
def claim_px4_instances(count: int) -> Iterator[tuple[int, ...]]:
    """Context manager form of `claim_free_instances` (released on exit)."""
    claim = claim_free_instances(count)
    try:
        yield claim.instances
    finally:
        claim.release()
