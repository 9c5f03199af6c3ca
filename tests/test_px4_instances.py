"""PX4 instances 0..9 claimed with lock files: parallel runs never share one, a SIGKILLed
claimer frees its instances (issue 15 item 5). No PX4 needed: the claims are ours."""

from __future__ import annotations

import subprocess
import sys

import pytest

from sitl_bridge.autopilot.px4 import Px4Error
from sitl_bridge.autopilot.px4.allocation import claim_free_instances, claim_instances
from sitl_bridge.autopilot.px4.fleet import Px4SitlFleet

HOLDER = """
import sys, time
from sitl_bridge.autopilot.px4.allocation import claim_free_instances
claim = claim_free_instances(int(sys.argv[1]))
print(*claim.instances, flush=True)
time.sleep(60)
"""


def _holder(count: int) -> tuple[subprocess.Popen, set[int]]:
    process = subprocess.Popen([sys.executable, "-c", HOLDER, str(count)], stdout=subprocess.PIPE, text=True)
    line = process.stdout.readline()
    assert line, "the holder could not claim instances"
    return process, {int(x) for x in line.split()}


def test_parallel_processes_get_disjoint_instances_and_a_kill_frees_them() -> None:
    first, a = _holder(2)
    second, b = None, set()
    try:
        second, b = _holder(2)
        assert len(a) == len(b) == 2 and not a & b
        assert all(0 <= i <= 9 for i in a | b)
        with pytest.raises(Px4Error, match=f"PX4 instance {min(a)} is in use"):
            claim_instances([min(a)])
        # An env that prefers a busy instance gets another free block.
        assert Px4SitlFleet.pick_instance_base(1, min(a)) not in a | b
        first.kill()  # SIGKILL: the kernel drops its locks
        first.wait(10)
        claim_instances(sorted(a)).release()
    finally:
        for process in (first, second):
            if process is not None:
                process.kill()
                process.wait(10)
                process.stdout.close()


def test_claims_in_one_process_do_not_overlap() -> None:
    one = claim_free_instances(3)
    try:
        two = claim_free_instances(3)
        assert not set(one.instances) & set(two.instances)
        two.release()
    finally:
        one.release()


def test_an_env_asking_for_an_instance_px4_cannot_serve_gets_one_in_0_to_9() -> None:
    """Benchmarks and tests ask for instances from 200 up (off the users' ones); real PX4 gives
    instances above 9 no API port of their own, so a px4 env must take a free block in 0..9."""
    base = Px4SitlFleet.pick_instance_base(2, 200)
    assert base >= 0 and base + 1 <= 9
