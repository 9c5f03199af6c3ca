"""`autopilot/px4/delivery.py` on real UDP sockets and real threads (no mocks, no PX4): the
/proc readings it relies on, and `wait_delivered` against a stand-in sender that sends late
from its own thread (as MAVSDK v4 does) and a stand-in receiver that handles slowly."""

from __future__ import annotations

import contextlib
import os
import select
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from sitl_bridge.autopilot.px4 import delivery
from sitl_bridge.autopilot.px4.delivery import (
    MAVSDK_THREAD,
    own_threads,
    register_sender,
    sender_threads,
    tag_mavsdk_io_thread,
    thread_syscall,
    threads_named,
    udp_rx_queue,
    wait_delivered,
)

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux") or not Path("/proc/net/udp").exists(),
    reason="reads Linux procfs",
)


def _bound_udp() -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    return sock


def _name_this_thread(name: str) -> None:
    Path(f"/proc/self/task/{threading.get_native_id()}/comm").write_text(name)


def _until(predicate, timeout_s: float = 5.0) -> None:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached"
        time.sleep(0.001)


def test_rx_queue_counts_unread_datagrams() -> None:
    with _bound_udp() as receiver, _bound_udp() as sender:
        port = receiver.getsockname()[1]
        assert udp_rx_queue(port) == 0
        for _ in range(3):
            sender.sendto(b"x" * 40, ("127.0.0.1", port))
        assert udp_rx_queue(port) > 0  # on loopback sendto queues it before returning
        receiver.recv(100)
        receiver.recv(100)
        assert udp_rx_queue(port) > 0
        receiver.recv(100)
        assert udp_rx_queue(port) == 0


def test_rx_queue_of_a_wildcard_socket_and_of_no_socket() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as receiver, _bound_udp() as sender:
        receiver.bind(("0.0.0.0", 0))
        port = receiver.getsockname()[1]
        sender.sendto(b"x", ("127.0.0.1", port))
        assert udp_rx_queue(port) > 0
    assert udp_rx_queue(port) is None  # closed: no such socket


def test_syscall_of_blocked_and_running_threads() -> None:
    with _bound_udp() as sock:
        poller = select.poll()
        poller.register(sock, select.POLLIN)
        tid: list[int] = []

        def blocked() -> None:
            tid.append(threading.get_native_id())
            poller.poll(5000)

        thread = threading.Thread(target=blocked)
        thread.start()
        _until(lambda: bool(tid) and thread_syscall("self", tid[0]) in delivery._syscalls("poll"))
        sock.sendto(b"wake", sock.getsockname())
        thread.join()
    _until(lambda: thread_syscall("self", tid[0]) is None)  # gone (once the OS thread exited)
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        _until(lambda: thread_syscall(busy.pid, busy.pid) == "running")  # not blocked
    finally:
        busy.kill()
        busy.wait()


@contextlib.contextmanager
def _stand_ins(
    handle_s: float, send_delay_s: float
) -> Iterator[tuple[int, threading.Event, list[int]]]:
    """A receiver thread named like PX4's (reads one datagram, takes `handle_s` to handle it,
    counts it) and a sender thread registered as MAVSDK's I/O thread (waits in epoll, sends
    `send_delay_s` after being asked). Yields (receiver port, ask-to-send event, handled)."""
    receiver, sender = _bound_udp(), _bound_udp()
    port = receiver.getsockname()[1]
    handled: list[int] = []
    stop = threading.Event()
    wake_r, wake_w = os.pipe()
    ask = threading.Event()

    def receive() -> None:
        _name_this_thread("mavlink_rcv_if0")
        poller = select.poll()
        poller.register(receiver, select.POLLIN)
        while not stop.is_set():
            if poller.poll(10):
                receiver.recv(100)
                time.sleep(handle_s)  # handling (PX4: parse and publish)
                handled.append(1)

    def send() -> None:
        register_sender(threading.get_native_id())
        epoll = select.epoll()
        epoll.register(wake_r, select.EPOLLIN)
        while not stop.is_set():
            if epoll.poll(0.01):
                os.read(wake_r, 1)
                time.sleep(send_delay_s)  # the I/O thread gets to it late (a busy machine)
                sender.sendto(b"setpoint", ("127.0.0.1", port))

    class Asking(threading.Event):
        def set(self) -> None:  # "set_velocity_ned": post to the I/O thread and return
            os.write(wake_w, b"!")

    ask = Asking()
    threads = [threading.Thread(target=receive), threading.Thread(target=send)]
    for thread in threads:
        thread.start()
    try:
        _until(lambda: len(threads_named("self", "mavlink_rcv_if", prefix=True)) == 1)
        _until(lambda: len(sender_threads()) == 1)
        yield port, ask, handled
    finally:
        stop.set()
        for thread in threads:
            thread.join()
        receiver.close()
        sender.close()
        os.close(wake_r)
        os.close(wake_w)


def test_wait_delivered_waits_for_a_late_send_and_a_slow_handler() -> None:
    with _stand_ins(handle_s=0.05, send_delay_s=0.03) as (port, ask, handled):
        for round_ in range(1, 4):
            ask.set()
            assert not handled[round_ - 1 :]  # nothing sent yet: rx_queue alone would say "done"
            start = time.monotonic()
            assert wait_delivered([(os.getpid(), port)], timeout_s=5.0)
            assert len(handled) == round_  # returned only once it was read and handled
            assert time.monotonic() - start >= 0.07


def test_wait_delivered_times_out_with_one_line() -> None:
    with _stand_ins(handle_s=2.0, send_delay_s=0.0) as (port, ask, _):
        ask.set()
        with pytest.raises(TimeoutError) as error:
            wait_delivered([(os.getpid(), port)], timeout_s=0.3)
        assert "\n" not in str(error.value)
        assert f"UDP {port}" in str(error.value) and "0.3 s" in str(error.value)


def test_unobservable_without_a_registered_sender() -> None:
    _until(lambda: sender_threads() == [])  # the stand-ins of other tests ended
    assert wait_delivered([(os.getpid(), 9)], timeout_s=1.0) is False


def test_tag_names_mavsdks_io_thread() -> None:
    mavsdk = pytest.importorskip("mavsdk")
    before = own_threads()
    instance = mavsdk.Mavsdk(
        mavsdk.Configuration.create_with_component_type(mavsdk.ComponentType.GROUND_STATION)
    )
    try:
        assert tag_mavsdk_io_thread(before)
        (tid,) = sender_threads()
        assert threads_named("self", MAVSDK_THREAD) == [str(tid)]
        assert thread_syscall("self", tid) in delivery._syscalls("epoll") | {"running"}
    finally:
        instance.destroy()
    _until(lambda: sender_threads() == [])  # forgotten once ended
