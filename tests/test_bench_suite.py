"""`sitl-bridge bench --smoke --json`: the one-run bench writes every key (speed itself is
the bench's business, never a unit test's)."""

from __future__ import annotations

import importlib.util
import json
import os
import signal
import subprocess
import sys
import time

import pytest


def test_bench_smoke_json_has_every_key(tmp_path, monkeypatch) -> None:
    from sitl_bridge.bench.suite import KEYS, SIZES

    monkeypatch.delenv("PX4_BIN", raising=False)
    out = tmp_path / "bench.json"
    proc = subprocess.run([sys.executable, "-m", "sitl_bridge", "bench", "--smoke", "--json", str(out)],
                          capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    result = json.loads(out.read_text())
    for key in KEYS:
        assert key in result, key
    assert result["px4"] == result["px4_standby"] == result["px4_parallel"] == {"skipped": "PX4_BIN not set"}
    bare = result["physics"]["rtf"]["median"]
    assert bare > 0 and result["physics"]["fraction_of_bare"]["median"] == 1.0
    for key in ("direct", "direct_ground_truth", "decision_0_1s", "batched", "stub", "train_steps_per_s",
                "train_vector_steps_per_s"):
        entry = result[key]
        assert set(entry["rtf"]) == {"median", "min", "max"}, key
        assert entry["rtf"]["min"] <= entry["rtf"]["median"] <= entry["rtf"]["max"], key
        assert entry["fraction_of_bare"]["median"] == entry["rtf"]["median"] / entry["bare_rtf_adjacent"], key
    # continuous 0.1 s decisions: ten env steps per simulated second, beside the 1 s direct case
    assert result["decision_0_1s"]["of_direct"] == (result["decision_0_1s"]["fraction_of_bare"]["median"]
                                                    / result["direct"]["fraction_of_bare"]["median"])
    assert result["train_steps_per_s"]["updates"] > 0  # DQN updates were part of the timing
    vector = result["train_vector_steps_per_s"]
    assert vector["updates"] > 0 and vector["num_envs"] > 1
    # batched at every N of the size, each as a fraction of the bare loop measured next to it
    by_n = result["batched"]["by_num_envs"]
    assert sorted(by_n, key=int) == [str(n) for n in SIZES["smoke"].batched_num_envs]
    for n, entry in by_n.items():
        assert entry["num_envs"] == int(n) and entry["reps"] == SIZES["smoke"].reps
        assert entry["fraction_of_bare"]["median"] == entry["rtf"]["median"] / result["batched"]["bare_rtf_adjacent"]
    assert result["batched"]["rtf"] == by_n[str(SIZES["smoke"].num_envs)]["rtf"]
    # other simulators: measured when they import, else skipped with the reason (never installed)
    for key, module in (("gym_pybullet_drones", "gym_pybullet_drones"), ("pyflyt", "PyFlyt")):
        if importlib.util.find_spec(module) is None:
            assert result[key] == {"skipped": f"{module} not installed (pip install {module.replace('_', '-')} "
                                              "to measure it)"}
        else:
            assert result[key]["rtf"]["median"] > 0
            assert result[key]["fraction_of_bare"]["median"] == (result[key]["rtf"]["median"]
                                                                 / result[key]["bare_rtf_adjacent"])
    assert set(result["reset_s"]) == {"direct", "stub"}
    for key in ("direct", "stub"):  # each reset after an ended episode of the random flight, timed
        resets = result[key]["episode_reset_s"]
        assert resets["count"] >= SIZES["smoke"].episode_resets, key
        assert 0 < resets["median"] <= resets["p95"] <= resets["max"], key
    parallel = result["parallel"]
    assert parallel["speedup_2_over_1"] > 0 and parallel["bare_speedup_2_over_1"] > 0
    assert parallel["fraction_of_bare_speedup"] == parallel["speedup_2_over_1"] / parallel["bare_speedup_2_over_1"]
    # the stub runs in this process: its CPU time per env step is all here
    cpu = result["stub"]["cpu_ms_per_step"]
    assert cpu["this_process"] > 0 and cpu["total"] == cpu["this_process"] + cpu["children"]


def test_scale_lengthens_every_new_case() -> None:
    from sitl_bridge.bench.suite import SIZES

    quick, longer = SIZES["quick"], SIZES["quick"].scaled(3.0)
    assert longer.sim_s == 3 * quick.sim_s and longer.peer_sim_s == 3 * quick.peer_sim_s
    assert longer.batched_steps == 3 * quick.batched_steps and longer.train_episodes == 3 * quick.train_episodes
    assert longer.batched_num_envs == quick.batched_num_envs == (1, 4, 16, 64)
    with pytest.raises(ValueError, match="--scale"):
        quick.scaled(0.0)


def test_cpu_time_counts_live_grandchildren() -> None:
    """With `standby=True` PX4 runs under the backend's worker processes: the CPU per env step
    must count their children too, while they are still running."""
    from sitl_bridge.bench.suite import _cpu_s

    burn = "import time; t = time.process_time(); exec('while time.process_time() - t < 0.5: pass'); time.sleep(30)"
    spawn = f"import subprocess, sys; subprocess.run([sys.executable, '-c', {burn!r}])"
    before = _cpu_s()
    child = subprocess.Popen([sys.executable, "-c", spawn], start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        while _cpu_s()[1] - before[1] < 0.5 and time.monotonic() < deadline:  # type: ignore[operator]
            time.sleep(0.1)
        assert _cpu_s()[1] - before[1] >= 0.5  # type: ignore[operator]
    finally:
        os.killpg(child.pid, signal.SIGKILL)  # the child and the grandchild, its own process group
        child.wait()


def test_px4_parallel_case_flies_two_px4_instances_at_once(px4_bin: str) -> None:
    """Each worker process flies its own PX4 instance, in 0..9 (own API port), never a shared one."""
    from sitl_bridge.bench.suite import SIZES, _px4_parallel_case

    result = _px4_parallel_case(SIZES["smoke"], 1.0, px4_bin)
    one, two = result["workers_1"], result["workers_2"]
    assert len(one["instances"]) == 1 and len(two["instances"]) == 2
    flown = [i for instances in two["instances"] for i in instances]
    assert len(set(flown)) == 2 and all(0 <= i <= 9 for i in flown)
    for entry in (one, two):
        assert entry["reps"] == SIZES["smoke"].reps
        assert 0 < entry["steps_per_s"]["min"] <= entry["steps_per_s"]["median"] <= entry["steps_per_s"]["max"]
        assert entry["rtf"]["median"] == pytest.approx(entry["steps_per_s"]["median"] * result["step_s"])
    assert result["speedup_2_over_1"] == two["rtf"]["median"] / one["rtf"]["median"]


def test_parallel_windows_run_every_worker_for_the_whole_window_together() -> None:
    """The parallel cases' timing: every worker runs each window for its full wall length,
    all released together, so no worker's tail runs alone (what made 2 workers look slower)."""
    from sitl_bridge.bench.suite import _bare_worker, _together

    window_s = 1.0
    with _together(_bare_worker, (2, window_s), 2) as results:
        runs = [results.get(timeout=120) for _ in range(4)]
    for window in (0, 1):
        mine = [r for r in runs if r[0] == window]
        assert len(mine) == 2
        starts, ends = [r[2] for r in mine], [r[3] for r in mine]
        assert all(end - start >= window_s for start, end in zip(starts, ends, strict=True))
        assert max(starts) - min(starts) < window_s / 2  # overlapping for most of the window
        assert all(r[1] > 0 for r in mine)  # each flew simulated time
