"""Shared test fixtures.

Tests that open sockets take a vehicle instance number from `free_instance` so that parallel
test runs (and a developer's own `sitl-bridge run`) never fight over ports; the ports of
instance i are those of `sitl_bridge.ports`.
"""

from __future__ import annotations

import os
import random
import signal

import pytest

from sitl_bridge.ports import instance_free

# A shell starts background jobs (`pytest ... &`) with SIGINT ignored, and children inherit an
# ignored signal through exec: the tests that stop `sitl-bridge run` with Ctrl-C would then wait
# for a process that never sees it. A handler here is reset to the default in every child.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


def instance_ports_free(instance: int) -> bool:
    """True when every port vehicle instance `instance` would use is free on 127.0.0.1
    (`sitl_bridge.ports`: a TCP port in TIME_WAIT counts as free, as our servers reuse it)."""
    return instance_free(instance)


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


@pytest.fixture
def px4_claim():
    """A held claim (`autopilot.allocation`) of one PX4 instance in 1..9 (own API port; 0 only
    when those are busy) for the whole test: a parallel run, or a test in another checkout on
    this machine, never starts a PX4 or a MAVLink client on it meanwhile. Pass it as a
    session's `instance_base` (the session adopts it)."""
    from sitl_bridge.autopilot.allocation import InstancesBusy, claim_free_instances
    from sitl_bridge.ports import PX4_LAST_OWN_API_INSTANCE

    try:
        claim = claim_free_instances(1, first=1, last=PX4_LAST_OWN_API_INSTANCE)
    except InstancesBusy as exc:
        pytest.skip(str(exc))
    with claim:
        yield claim


@pytest.fixture
def px4_instance(px4_claim) -> int:
    """The instance of `px4_claim`, for tests that drive a `Px4Fleet` themselves."""
    return px4_claim.base


@pytest.fixture(scope="session", autouse=True)
def compiled_kernels() -> None:
    """Compile (or load) the stub's numba kernels once, in this process, before any test. A cold
    cache costs 20-30 s of CPU; a stub started as a child process would otherwise pay it inside
    a test's connect timeout. Children load the kernels from the same on-disk cache."""
    from sitl_bridge.session import SimSession

    with SimSession("empty", autopilot="stub", speed_factor=0, instance_base=pick_free_instances(1)) as session:
        session.run_for(0.1)
