"""Vehicle instances are claimed with lock files (`autopilot.allocation`), and the pick is the
claim: processes picking at the same moment never get overlapping instances,
a SIGKILLed holder frees its own, an env holds its claim from its first reset to its close and
its session adopts it instead of claiming again. Real processes, sockets and sessions; the last
test needs real PX4 (PX4_BIN)."""

from __future__ import annotations

import fcntl
import multiprocessing as mp
import os
import random
import threading
import time
from pathlib import Path

import pytest

from sitl_bridge.autopilot.allocation import (
    LOCK_DIR,
    SEARCH_LOCK_NAME,
    InstanceClaim,
    InstancesBusy,
    claim_free_instances,
    claim_instances,
)
from sitl_bridge.autopilot.px4.fleet import Px4SitlFleet
from sitl_bridge.ports import MAX_INSTANCE, PX4_LAST_OWN_API_INSTANCE

WORLDS = Path(__file__).resolve().parents[1] / "worlds"
PROCESSES = 8
PER_PROCESS = 2
"""Instances each process claims: blocks, so a half-overlap would show too."""


def _claim_after_barrier(barrier, results, first: int, last: int) -> None:  # noqa: ANN001 - mp proxies
    """In a fresh process: wait for the others, pick + claim at once, report, hold until killed."""
    barrier.wait(timeout=120)
    try:
        claim = claim_free_instances(PER_PROCESS, first, last)
    except InstancesBusy as exc:
        results.put((os.getpid(), (), str(exc)))
        return
    results.put((os.getpid(), claim.instances, ""))
    time.sleep(300)  # holding `claim` (a live local) until the test kills this process


def _free_window(size: int) -> int:
    """First instance of `size` consecutive instances nobody claims or uses now, at random in
    20..MAX_INSTANCE (off the low ones users and PX4 run on; other test runs pick elsewhere)."""
    rng = random.Random()
    for _ in range(100):
        first = rng.randrange(20, MAX_INSTANCE - size + 2)
        try:
            claim_instances(range(first, first + size), check_free=True).release()
        except InstancesBusy:
            continue
        return first
    pytest.skip(f"no {size} consecutive free vehicle instances")


def test_processes_picking_at_the_same_moment_never_overlap_and_a_kill_frees_a_claim() -> None:
    window = _free_window(PROCESSES * PER_PROCESS + 8)  # room for every process, a little to spare
    first, last = window, window + PROCESSES * PER_PROCESS + 7
    ctx = mp.get_context("spawn")
    barrier, results = ctx.Barrier(PROCESSES), ctx.Queue()
    processes = [ctx.Process(target=_claim_after_barrier, args=(barrier, results, first, last), daemon=True)
                 for _ in range(PROCESSES)]
    for process in processes:
        process.start()
    try:
        reports = [results.get(timeout=120) for _ in range(PROCESSES)]
        assert [error for _, _, error in reports if error] == []
        held = {pid: set(instances) for pid, instances, _ in reports}
        claimed = [i for instances in held.values() for i in instances]
        assert len(claimed) == len(set(claimed)) == PROCESSES * PER_PROCESS, held  # no instance twice
        assert all(first <= i <= last for i in claimed), (sorted(claimed), first, last)
        victim = next(p for p in processes if p.pid == min(held, key=lambda pid: min(held[pid])))
        survivor = next(pid for pid in held if pid != victim.pid)
        with pytest.raises(InstancesBusy, match=f"instance {min(held[victim.pid])} is in use"):
            claim_instances(sorted(held[victim.pid]))
        victim.kill()  # SIGKILL: no code of the holder runs, the kernel drops its lock
        victim.join(10)
        claim_instances(sorted(held[victim.pid])).release()  # free again
        with pytest.raises(InstancesBusy):
            claim_instances(sorted(held[survivor]))  # the others still hold theirs
    finally:
        for process in processes:
            process.kill()
            process.join(10)


def test_searches_take_turns_so_one_never_meets_anothers_passing_locks() -> None:
    """A search holds the machine's search lock throughout: one that runs while another search
    locks and lets go block after block would take those passing locks for claims and skip free
    blocks (two searchers one instance apart leapfrogged out of their whole range)."""
    first = _free_window(2)
    turn = os.open(LOCK_DIR / SEARCH_LOCK_NAME, os.O_RDONLY | os.O_CREAT | os.O_CLOEXEC, 0o666)
    found: list[InstanceClaim] = []
    try:
        fcntl.flock(turn, fcntl.LOCK_EX)  # another search, mid-way
        search = threading.Thread(
            target=lambda: found.append(claim_free_instances(2, first, first + 1))
        )
        search.start()
        search.join(0.5)
        assert search.is_alive() and not found  # waits for its turn ...
    finally:
        os.close(turn)
    search.join(10)
    assert [claim.instances for claim in found] == [(first, first + 1)]  # ... then searches
    found[0].release()


def test_claims_in_one_process_do_not_overlap_and_release_frees_them() -> None:
    with claim_free_instances(3, 20) as one, claim_free_instances(3, 20) as two:
        assert not set(one.instances) & set(two.instances)
    assert not one.held and not two.held
    claim_instances([*one.instances, *two.instances]).release()


def test_a_px4_env_claims_in_0_to_9_whatever_it_prefers() -> None:
    """Benchmarks prefer instances from 200 up (off the users' ones); real PX4 gives instances
    above 9 no API port of their own, so a px4 env must take a free block in 0..9."""
    try:
        claim = claim_free_instances(2, 200, Px4SitlFleet.last_instance)
    except InstancesBusy as exc:
        pytest.skip(str(exc))
    with claim:
        assert claim.base >= 0 and claim.instances[-1] <= PX4_LAST_OWN_API_INSTANCE


def test_a_session_adopts_a_held_claim_and_claims_a_bare_instance_itself(free_instances) -> None:
    from sitl_bridge.session import SimSession  # here: the claiming processes above start lighter

    base = free_instances(2)
    with claim_instances([base]) as claim:
        with SimSession("empty", autopilot="stub", speed_factor=0, instance_base=claim) as session:
            assert session.instances == [base]
            session.run_for(0.2)
        assert claim.held  # the caller's: the session left it alone
        with pytest.raises(InstancesBusy):
            claim_instances([base])
    with SimSession("empty", autopilot="stub", speed_factor=0, instance_base=base + 1), \
            pytest.raises(InstancesBusy):  # a bare number: the session claimed it itself ...
        claim_instances([base + 1])
    claim_instances([base, base + 1]).release()  # ... until close()
    released = InstanceClaim([base], [])
    released.release()
    with pytest.raises(InstancesBusy, match="does not hold"):
        SimSession("empty", autopilot="stub", speed_factor=0, instance_base=released).start()


def test_envs_preferring_the_same_instance_get_their_own_held_until_close(free_instances) -> None:
    """What `make_vec_env` copies and parallel sweep runs rely on: the pick is a claim."""
    from sitl_bridge.envs import make_env

    base = free_instances(2)
    envs = [make_env(WORLDS / "empty.yaml", autopilot="stub", speed_factor=0.0, instance_base=base)
            for _ in range(2)]
    try:
        for env in envs:
            env.reset(seed=0)
        one, two = (env.backend.claim for env in envs)
        assert one.instances == (base,) and not set(one.instances) & set(two.instances)
        assert [env.backend.session.instances for env in envs] == [list(one.instances), list(two.instances)]
        with pytest.raises(InstancesBusy):
            claim_instances(one.instances)
    finally:
        for env in envs:
            env.close()
    claim_instances([*one.instances, *two.instances]).release()


def _px4_env_after_barrier(barrier, results, px4_bin: str) -> None:  # noqa: ANN001 - mp proxies
    """In a fresh process: start a px4 env together with the others, report its instances."""
    from sitl_bridge.envs import make_env

    env = None
    try:
        env = make_env(WORLDS / "empty.yaml", autopilot="px4", px4_bin=px4_bin, speed_factor=0.0, instance_base=1)
        barrier.wait(timeout=120)
        env.reset(seed=0)
        results.put((env.backend.claim.instances, tuple(env.backend.session.instances), ""))
        barrier.wait(timeout=300)  # both flying at once before either closes
    except Exception as exc:
        barrier.abort()
        results.put(((), (), f"{type(exc).__name__}: {exc}"))
    finally:
        if env is not None:
            env.close()


@pytest.mark.px4
@pytest.mark.timeout(600)
def test_px4_envs_started_at_the_same_moment_fly_on_their_own_instances(px4_bin: str) -> None:
    ctx = mp.get_context("spawn")
    barrier, results = ctx.Barrier(2), ctx.Queue()
    processes = [ctx.Process(target=_px4_env_after_barrier, args=(barrier, results, px4_bin)) for _ in range(2)]
    for process in processes:
        process.start()
    try:
        reports = [results.get(timeout=500) for _ in processes]
    finally:
        for process in processes:
            process.join(60)
            if process.is_alive():
                process.kill()
                process.join(10)
    assert [error for _, _, error in reports if error] == []
    (claim_a, flown_a, _), (claim_b, flown_b, _) = reports
    assert claim_a == flown_a and claim_b == flown_b  # the sessions flew the claims they adopted
    assert not set(flown_a) & set(flown_b) and max(*flown_a, *flown_b) <= PX4_LAST_OWN_API_INSTANCE
