"""Setpoint delivery to a held real PX4, observed through Linux procfs instead of slept for.

A held lockstep freezes PX4's clock, but PX4's MAVLink receiver reads its UDP socket in wall
time. New velocity setpoints (an env's action) must have been taken in by PX4 before the
next physics step, or the same action would act at different steps from run to run. Two
hops can lag under load, and both are observed here:

1. MAVSDK (v4) does not send from the calling thread: `set_velocity_ned` posts the message to
   its I/O thread (an Asio io_context) and returns, almost always before the datagram exists
   (measured: 994 of 1000 calls). The I/O thread runs its queue in order and only blocks in
   `epoll_wait` once the queue is empty, so once every MAVSDK I/O thread of this process is
   seen blocked in `epoll_wait`, everything posted before was handed to the kernel (on
   loopback `sendto` queues the datagram on the receiving socket before it returns). The
   client registers that thread (`tag_mavsdk_io_thread`, when it creates its `Mavsdk`) by
   thread id: a name would not do, threads it starts later inherit it.
2. PX4's receiver threads (`mavlink_rcv_if<k>`) read one datagram per `recvfrom`, handle
   (publish) its messages, and only then block in `poll` again, which they do not while data
   is queued: the datagram and the wakeup of its reader were both queued before the send
   returned. So once every receiver thread of the process is then seen blocked in `poll`,
   the setpoint was read and published; as a cross-check PX4's API socket must also hold no
   unread data (`rx_queue` 0 in /proc/net/udp).

Both states are read from /proc/<pid>/task/<tid>/syscall (the number of the system call a
blocked thread sleeps in; "running" otherwise), which Linux lets a process read for its own
threads and its children's. Where any of it cannot be read (not Linux, another CPU
architecture, no registered MAVSDK thread, no permission) `wait_delivered` says so and the
caller falls back to a fixed wall wait.

Not covered: a kernel that defers loopback delivery to ksoftirqd (heavy network load) queues
the datagram after the send returned; the fixed wait had the same blind spot.
"""

from __future__ import annotations

import contextlib
import os
import platform
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

MAVSDK_THREAD = "mavsdk"
"""Name given to MAVSDK's I/O thread (for `top -H`; the threads it starts inherit it)."""
PX4_RECEIVER_PREFIX = "mavlink_rcv_if"
"""PX4's MAVLink receiver threads are named mavlink_rcv_if<k> (mavlink_receiver.cpp)."""
POLL_S = 0.0002
"""Wall seconds between looks at procfs while waiting."""

_PROC = Path("/proc")
_senders: set[int] = set()  # thread ids of the MAVSDK I/O threads of this process
_receivers: dict[int, list[str]] = {}  # PX4 pid -> its receiver threads' ids
# System call numbers (the first field of /proc/.../syscall) a thread blocks in, per CPU
# architecture: asio's reactor waits in epoll_wait, PX4's receiver in poll (glibc may use ppoll).
_SYSCALLS = {
    "x86_64": {"epoll": frozenset({"232", "281", "441"}), "poll": frozenset({"7", "271"})},
    "aarch64": {"epoll": frozenset({"22", "441"}), "poll": frozenset({"73"})},
}


class DeliveryUnobservable(Exception):
    """Something the check needs cannot be read here (the caller waits a fixed time instead)."""


def _syscalls(kind: str) -> frozenset[str]:
    table = _SYSCALLS.get(platform.machine())
    if table is None:
        raise DeliveryUnobservable(f"no system call table for {platform.machine()}")
    return table[kind]


def udp_rx_queue(port: int, host: str = "127.0.0.1") -> int | None:
    """Bytes queued unread on the UDP socket bound to `port` (on `host` or the wildcard
    address), from /proc/net/udp and udp6; None when no such socket exists. Raises
    `DeliveryUnobservable` without /proc/net/udp (not Linux)."""
    try:
        text = (_PROC / "net" / "udp").read_text()
    except OSError as exc:
        raise DeliveryUnobservable(f"/proc/net/udp: {exc}") from exc
    with contextlib.suppress(OSError):
        text += (_PROC / "net" / "udp6").read_text()
    port_hex = f"{port:04X}"
    wanted = {_hex_ipv4(host), "00000000", "0" * 32, "0000000000000000FFFF0000" + _hex_ipv4(host)}
    for line in text.splitlines():
        fields = line.split()
        # sl local_address rem_address st tx_queue:rx_queue ...
        if len(fields) < 5 or ":" not in fields[1]:
            continue
        address, _, local_port = fields[1].rpartition(":")
        if local_port == port_hex and address in wanted:
            return int(fields[4].partition(":")[2], 16)
    return None


def _hex_ipv4(host: str) -> str:
    """/proc/net/udp's spelling of an IPv4 address (little-endian hex of the 32-bit word)."""
    octets = [int(part) for part in host.split(".")]
    return "".join(f"{octet:02X}" for octet in reversed(octets))


def thread_syscall(pid: int | str, tid: int | str) -> str | None:
    """The system call thread `tid` of process `pid` is blocked in (its number, as text),
    'running' when it is not blocked, None when the thread is gone. Raises
    `DeliveryUnobservable` when the file cannot be read for another reason (permission)."""
    try:
        return thread_file(pid, tid, "syscall").read_text().split(maxsplit=1)[0]
    except (FileNotFoundError, ProcessLookupError):
        return None
    except (OSError, IndexError) as exc:
        raise DeliveryUnobservable(f"/proc/{pid}/task/{tid}/syscall: {exc}") from exc


def thread_ids(pid: int | str) -> list[str]:
    """Thread ids of process `pid` ([] when it is gone)."""
    try:
        return os.listdir(_PROC / str(pid) / "task")
    except OSError:
        return []


def thread_file(pid: int | str, tid: int | str, name: str) -> Path:
    """/proc/<pid>/task/<tid>/<name>."""
    return _PROC / str(pid) / "task" / str(tid) / name


def threads_named(pid: int | str, name: str, *, prefix: bool = False) -> list[str]:
    """Thread ids of process `pid` whose name is `name` (or starts with it)."""
    found = []
    for tid in thread_ids(pid):
        try:
            comm = thread_file(pid, tid, "comm").read_text().rstrip("\n")
        except OSError:
            continue
        if comm == name or (prefix and comm.startswith(name)):
            found.append(tid)
    return found


def own_threads() -> set[str]:
    """Thread ids of this process ('' set where /proc is missing)."""
    try:
        return set(os.listdir(_PROC / "self" / "task"))
    except OSError:
        return set()


def register_sender(tid: int) -> None:
    """Count thread `tid` of this process as a MAVSDK I/O thread (`wait_delivered` waits
    until it blocks in `epoll_wait`); forgotten once it has ended."""
    _senders.add(tid)


def sender_threads() -> list[int]:
    """The registered MAVSDK I/O threads still alive."""
    for tid in list(_senders):
        if not (_PROC / "self" / "task" / str(tid)).exists():
            _senders.discard(tid)
    return sorted(_senders)


def tag_mavsdk_io_thread(before: Iterable[str], timeout_s: float = 2.0) -> bool:
    """Register MAVSDK's I/O thread (`register_sender`) and name it `MAVSDK_THREAD`: the
    thread started since `before` (`own_threads()` taken just before creating the `Mavsdk`)
    that blocks in `epoll_wait` (waiting up to `timeout_s` for it to get there). False where
    it cannot be found."""
    new = own_threads() - set(before)
    if not new:
        return False
    try:
        epoll = _syscalls("epoll")
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for tid in new:
                if thread_syscall("self", tid) in epoll:
                    register_sender(int(tid))
                    with contextlib.suppress(OSError):
                        (_PROC / "self" / "task" / tid / "comm").write_text(MAVSDK_THREAD)
                    return True
            time.sleep(0.001)
    except DeliveryUnobservable:
        return False
    return False


def _blocked_in(pid: int | str, tid: str, calls: frozenset[str]) -> bool:
    """Thread `tid` is blocked in one of `calls`, or gone."""
    call = thread_syscall(pid, tid)
    return call is None or call in calls


def _receiver_threads(pid: int) -> list[str]:
    """PX4 process `pid`'s MAVLink receiver threads (looked up once per PX4 process: they
    start at boot, before any setpoint can be sent)."""
    readers = _receivers.get(pid)
    if readers is None or not all((_PROC / str(pid) / "task" / tid).exists() for tid in readers):
        if len(_receivers) > 64:
            _receivers.clear()  # PX4 processes of long ago
        readers = _receivers[pid] = threads_named(pid, PX4_RECEIVER_PREFIX, prefix=True)
    return readers


def _wait(done: Callable[[], bool], deadline: float, what: str, timeout_s: float) -> None:
    while not done():
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what} within {timeout_s:g} s (wall)")
        time.sleep(POLL_S)


def wait_delivered(receivers: Sequence[tuple[int, int]], timeout_s: float) -> bool:
    """Wait until what MAVSDK was asked to send so far was read and handled by PX4:
    `receivers` is (PX4 pid, its API port `api_bind_port(instance)`) per vehicle. True once
    observed; False (at once, or once something turns out unreadable) where it cannot be
    observed here. Raises TimeoutError (one line) after `timeout_s` wall seconds."""
    deadline = time.monotonic() + timeout_s
    try:
        epoll, poll = _syscalls("epoll"), _syscalls("poll")
        senders = sender_threads()
        if not senders:
            return False
        # 1. MAVSDK sent it: every I/O thread back in epoll_wait (or gone: closed client).
        for tid in senders:
            _wait(
                lambda tid=tid: _blocked_in("self", tid, epoll),
                deadline,
                "MAVSDK's I/O thread did not go idle (send the setpoints)",
                timeout_s,
            )
        # 2. PX4 read and handled it: every receiver thread back in poll, its socket empty.
        for pid, port in receivers:
            readers = _receiver_threads(pid)
            if not readers:
                return False

            def taken_in(pid: int = pid, port: int = port, readers: list[str] = readers) -> bool:
                if not all(_blocked_in(pid, tid, poll) for tid in readers):
                    return False
                queued = udp_rx_queue(port)
                if queued is None:
                    raise DeliveryUnobservable(f"no UDP socket on port {port}")
                return queued == 0

            _wait(
                taken_in,
                deadline,
                f"PX4 (pid {pid}) did not take in the setpoints on UDP {port}",
                timeout_s,
            )
    except DeliveryUnobservable:
        return False
    return True


__all__ = [
    "MAVSDK_THREAD",
    "POLL_S",
    "PX4_RECEIVER_PREFIX",
    "DeliveryUnobservable",
    "own_threads",
    "register_sender",
    "sender_threads",
    "tag_mavsdk_io_thread",
    "thread_file",
    "thread_ids",
    "thread_syscall",
    "threads_named",
    "udp_rx_queue",
    "wait_delivered",
]
