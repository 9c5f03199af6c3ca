"""Shared test fixtures.

Tests that open sockets take a vehicle instance number from `free_instance` so that parallel
test runs (and a developer's own `sitl-bridge run`) never fight over ports. Instance i uses
TCP 4560+i (HIL link), UDP 14580+i (autopilot API bind), UDP 14540+i (API client),
UDP 18570+i (GCS link bind).
"""

from __future__ import annotations

import os
import random
import socket

import pytest

HIL_BASE_PORT = 4560
API_BIND_BASE_PORT = 14580
API_CLIENT_BASE_PORT = 14540
GCS_BIND_BASE_PORT = 18570


def _port_free(port: int, kind: int) -> bool:
    with socket.socket(socket.AF_INET, kind) as sock:
        # A TCP port left in TIME_WAIT by an earlier test is reusable, as our servers set
        # SO_REUSEADDR too; without it such a port would look busy.
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def instance_ports_free(instance: int) -> bool:
    """True when every port vehicle instance `instance` would use is free on 127.0.0.1."""
    return (
        _port_free(HIL_BASE_PORT + instance, socket.SOCK_STREAM)
        and _port_free(API_BIND_BASE_PORT + instance, socket.SOCK_DGRAM)
        and _port_free(API_CLIENT_BASE_PORT + instance, socket.SOCK_DGRAM)
        and _port_free(GCS_BIND_BASE_PORT + instance, socket.SOCK_DGRAM)
    )


# The MAVLink system id is 1 + instance and must fit in one byte.
MAX_INSTANCE = 253


def pick_free_instances(count: int) -> int:
    """First instance of `count` consecutive free instances, chosen at random in 20..253."""
    rng = random.Random(os.getpid() ^ random.getrandbits(32))
    for _ in range(200):
        first = rng.randrange(20, MAX_INSTANCE - count + 2)
        if all(instance_ports_free(first + k) for k in range(count)):
            return first
    raise RuntimeError("no free block of vehicle instances on 127.0.0.1")


@pytest.fixture
def free_instance() -> int:
    """A vehicle instance number whose ports are all free."""
    return pick_free_instances(1)


@pytest.fixture
def free_instances():
    """Call with a count: returns the first of that many consecutive free instances."""
    return pick_free_instances


@pytest.fixture
def px4_bin() -> str:
    """Path of a real PX4 SITL binary from PX4_BIN; skips the test without one."""
    path = os.environ.get("PX4_BIN")
    if not path or not os.path.isfile(path):
        pytest.skip("PX4_BIN not set to a px4_sitl_default bin/px4; real-PX4 test skipped")
    return path
