"""One core per worker for parallel PX4-backed runs (`sitl_bridge.cores`), on real processes."""

from __future__ import annotations

import multiprocessing as mp
import os
import time
from concurrent.futures import ProcessPoolExecutor

import pytest

from sitl_bridge.cores import core_counter, pin_next_core, pins_workers, usable_cores

pytestmark = pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="pinning is Linux's")


def _affinity(pause_s: float) -> tuple[int, ...]:
    time.sleep(pause_s)  # long enough that every worker of the pool gets tasks
    return tuple(sorted(os.sched_getaffinity(0)))


def test_only_px4_pools_with_no_more_workers_than_cores_pin() -> None:
    cores = len(usable_cores())
    assert pins_workers("px4", 2) == (cores >= 2)
    assert not pins_workers("px4", 1)  # a single run keeps every core
    assert not pins_workers("px4", cores + 1)  # more workers than cores: the scheduler shares them
    assert not pins_workers("direct", 2) and not pins_workers("stub", 2)


def test_each_pool_worker_pins_itself_to_its_own_core() -> None:
    cores = usable_cores()
    ctx = mp.get_context("spawn")
    workers = min(2, len(cores))
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=pin_next_core,
                             initargs=(core_counter(ctx, ["px4"], workers),)) as pool:
        seen = set(pool.map(_affinity, [0.1] * 8 * workers))
    assert all(len(mask) == 1 for mask in seen)  # every task ran on one core ...
    assert len(seen) == workers  # ... its worker's own
    assert {core for mask in seen for core in mask} <= set(cores)
    assert _affinity(0) == tuple(cores)  # this process was not pinned
