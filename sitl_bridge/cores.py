"""One core per worker for parallel PX4-backed runs.

A PX4-backed env and its PX4 process run in lockstep: the simulator steps, PX4 answers, the
simulator steps again, so one such pair gains little from a second core. Two pairs left to the
scheduler on two cores interfere instead (threads migrating between cores, each waking
behind the other pair's work): on this project's 2-core machine, two `px4` bench workers flew
18.0 env steps/s together unpinned and 33.0 with each worker (and so its PX4, which inherits
the mask) pinned to its own core; one pinned worker alone flew 18.8 against 16.2 unpinned
(`sitl-bridge bench`'s `px4_parallel`, 2026-11-28, one run after the other).

So process pools of PX4-backed runs (`rl.experiments.sweep`, `rl.experiments.results`, the bench) pin each
worker to its own core when there are no more workers than cores (`pins_workers`). Pinning
is Linux's `sched_setaffinity`; elsewhere nothing is pinned.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from typing import Any

PINNED_KINDS = ("px4",)
"""Autopilot kinds whose workers are pinned: an external autopilot process in lockstep."""


def usable_cores() -> list[int]:
    """The cores this process may run on (all of the machine's where it cannot tell)."""
    if hasattr(os, "sched_getaffinity"):
        return sorted(os.sched_getaffinity(0))
    return list(range(os.cpu_count() or 1))


def pins_workers(autopilot: str, workers: int) -> bool:
    """Whether a pool of `workers` processes flying `autopilot` pins each to its own core."""
    return autopilot in PINNED_KINDS and 1 < workers <= len(usable_cores()) and hasattr(os, "sched_setaffinity")


def pin_to_own_core(index: int) -> int | None:
    """Pin this process, and every process and thread it starts from now on, to the
    `index`-th usable core (round robin); returns that core, None where nothing was pinned."""
    if not hasattr(os, "sched_setaffinity"):
        return None
    cores = usable_cores()
    core = cores[index % len(cores)]
    os.sched_setaffinity(0, {core})
    return core


def core_counter(ctx: Any, autopilots: Iterable[str], workers: int) -> Any:
    """For a process pool of `workers` made with the multiprocessing context `ctx`, its tasks
    flying `autopilots`: the argument of its initializer's `pin_next_core` (a shared counter
    where every task's kind pins, `pins_workers`; else None: nothing pinned)."""
    return ctx.Value("i", 0) if all(pins_workers(kind, workers) for kind in autopilots) else None


def pin_next_core(counter: Any) -> int | None:
    """In a pool worker (its initializer): pin it to the next core in turn (`core_counter`;
    None: not pinned)."""
    if counter is None:
        return None
    with counter.get_lock():
        index = counter.value
        counter.value += 1
    return pin_to_own_core(index)
