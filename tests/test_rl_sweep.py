"""`sitl-bridge sweep`: parallel runs with their own run dirs and a summary, resume of a
half-finished sweep, a failing run reported without stopping the others, the same through Ray."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from sitl_bridge.data_paths import worlds_dir

WORLD = str(worlds_dir() / "empty.yaml")
TINY = ["--episodes", "2", "--eval-every", "0", "--eval-episodes", "0"]


def _sweep(root: Path, *extra: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sitl_bridge", "sweep", WORLD, "--out", str(root), *TINY, *extra],
                          capture_output=True, text=True, timeout=300, env=env)


def _summary(root: Path) -> dict[int, dict]:
    return {row["seed"]: row for row in json.loads((root / "summary.json").read_text())}


def _episodes(run_dir: str) -> int:
    return len((Path(run_dir) / "episodes.jsonl").read_text().splitlines())


def test_two_seed_sweep_then_rerun_skips(tmp_path) -> None:
    root = tmp_path / "sweep"
    proc = _sweep(root, "--seeds", "0-1", "--workers", "2")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    rows = _summary(root)
    assert set(rows) == {0, 1}
    for seed, row in rows.items():
        assert row["status"] == "done" and row["episodes"] == 2
        run_dir = Path(row["run_dir"])
        assert run_dir.parent == root / "base" / f"seed{seed}"
        assert _episodes(row["run_dir"]) == 2
    assert rows[0]["run_dir"] != rows[1]["run_dir"]
    assert "2/2 runs finished" in proc.stdout

    again = _sweep(root, "--seeds", "0-1", "--workers", "2")
    assert again.returncode == 0, again.stderr
    assert all(row["status"] == "skipped" for row in _summary(root).values())
    assert all(len(list((root / "base" / f"seed{s}").glob("empty__*"))) == 1 for s in (0, 1))


def test_half_finished_sweep_resumes(tmp_path) -> None:
    """Seed 0 finished; seed 1 was killed after one episode (a run dir, no done.json)."""
    from sitl_bridge.rl.common.drones_env import scenario_env_factory
    from sitl_bridge.rl.learner.config import load_train_config
    from sitl_bridge.rl.training.run_dir import RunSpec
    from sitl_bridge.rl.training.trainer import Trainer

    root = tmp_path / "sweep"
    assert _sweep(root, "--seeds", "0", "--workers", "1").returncode == 0
    config = load_train_config(WORLD, {"episodes": 2, "eval_every": 0, "eval_episodes": 0})
    with Trainer.start(root / "base" / "seed1", RunSpec(world=WORLD, seed=1), config,
                       scenario_env_factory(WORLD), progress=False) as trainer:
        trainer.run_episode()
        trainer.save_checkpoint()
        killed_dir = trainer.run_dir

    proc = _sweep(root, "--seeds", "0-1", "--workers", "2")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    rows = _summary(root)
    assert rows[0]["status"] == "skipped"
    assert rows[1]["status"] == "done" and Path(rows[1]["run_dir"]) == killed_dir
    assert _episodes(rows[1]["run_dir"]) == 2  # one episode before the kill, one after: resumed


def test_failed_run_is_reported_and_others_finish(tmp_path) -> None:
    torch = pytest.importorskip("torch")
    if torch.cuda.is_available():
        pytest.skip("needs a machine without CUDA (the failing grid point asks for it)")
    grid = tmp_path / "grid.yaml"
    grid.write_text("device: [cpu, cuda]\n")
    root = tmp_path / "sweep"
    proc = _sweep(root, "--seeds", "0", "--grid", str(grid), "--workers", "2")
    assert proc.returncode == 1
    rows = {row["point"]: row for row in json.loads((root / "summary.json").read_text())}
    assert rows["device=cpu"]["status"] == "done"
    assert rows["device=cuda"]["status"] == "failed" and rows["device=cuda"]["error"]
    assert "1/1 runs finished" in proc.stdout and "0/1 runs finished" in proc.stdout


def test_bad_seeds_and_grid_are_one_line_errors(tmp_path) -> None:
    grid = tmp_path / "grid.yaml"
    grid.write_text("gamma: [0.9, 7]\n")
    proc = _sweep(tmp_path / "s", "--seeds", "0", "--grid", str(grid))
    assert proc.returncode == 2 and "gamma" in proc.stderr and str(grid) in proc.stderr
    proc = _sweep(tmp_path / "s", "--seeds", "5-2")
    assert proc.returncode == 2 and "--seeds" in proc.stderr


def test_two_seed_sweep_on_rays_local_cluster(tmp_path) -> None:
    """A local cluster of its own: RAY_ADDRESS=local, so that neither a RAY_ADDRESS of the caller
    nor a cluster started with `ray start` on this machine (which Ray joins by default) is used."""
    pytest.importorskip("ray")
    root = tmp_path / "sweep"
    own_cluster = {**os.environ, "RAY_ADDRESS": "local"}
    proc = _sweep(root, "--seeds", "0-1", "--backend", "ray", env=own_cluster)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    rows = _summary(root)
    for seed in (0, 1):
        assert rows[seed]["status"] == "done"
        assert Path(rows[seed]["run_dir"]).parent == root / "base" / f"seed{seed}"
        assert _episodes(rows[seed]["run_dir"]) == 2


def _training_children(root: Path) -> list[int]:
    """Pids of `sitl-bridge train` processes writing under `root`."""
    pids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                cmdline = (entry / "cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if b"train" in cmdline and any(str(root).encode() in part for part in cmdline):
                pids.append(int(entry.name))
    return pids


def test_supervised_sweep_restarts_a_killed_run_from_its_checkpoint(tmp_path) -> None:
    import os
    import signal
    import time

    root = tmp_path / "sweep"
    command = [sys.executable, "-m", "sitl_bridge", "sweep", WORLD, "--out", str(root), "--episodes", "6",
               "--eval-every", "0", "--eval-episodes", "0", "--seeds", "0", "--workers", "1", "--watchdog"]
    sweep = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 240
        killed = False
        while not killed and time.monotonic() < deadline and sweep.poll() is None:
            logs = list(root.glob("*/seed0/*/episodes.jsonl"))
            if logs and len(logs[0].read_text().splitlines()) >= 2:
                for pid in _training_children(root):
                    os.kill(pid, signal.SIGKILL)
                    killed = True
            time.sleep(0.2)
        assert killed, "the training child was never seen"
        out, err = sweep.communicate(timeout=300)
    finally:
        if sweep.poll() is None:
            sweep.kill()
    assert sweep.returncode == 0, err
    (row,) = json.loads((root / "summary.json").read_text())
    assert row["status"] == "done" and row["episodes"] == 6
    assert row["restarts"] >= 1
    episodes = [json.loads(line)["episode"] for line in (Path(row["run_dir"]) / "episodes.jsonl").read_text().splitlines()]
    assert episodes == list(range(6))  # restarted from its checkpoint: no gap, no duplicate
    assert (Path(row["run_dir"]) / "watchdog.jsonl").read_text().count("killed by signal 9") >= 1


def test_supervised_sweep_needs_the_direct_backend(tmp_path) -> None:
    proc = _sweep(tmp_path / "s", "--seeds", "0", "--watchdog", "--autopilot", "stub")
    assert proc.returncode == 2 and "supervised sweeps run the direct backend only" in proc.stderr


def _children(pid: int) -> list[int]:
    """Processes whose parent is `pid` (Linux /proc)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            found.append(int(stat.parent.name))
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="parent-death signal is Linux only")
def test_killed_sweep_takes_its_workers_with_it(tmp_path) -> None:
    import signal
    import time

    root = tmp_path / "sweep"
    proc = subprocess.Popen([sys.executable, "-m", "sitl_bridge", "sweep", WORLD, "--out", str(root),
                             "--episodes", "100000", "--eval-every", "0", "--eval-episodes", "0",
                             "--seeds", "0-1", "--workers", "2"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    workers: list[int] = []
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and len(list(root.glob("base/seed*/*/episodes.jsonl"))) < 2:
            time.sleep(0.5)
        workers = [pid for pid in _children(proc.pid) if "spawn_main" in Path(f"/proc/{pid}/cmdline").read_text()]
        assert len(workers) == 2, "both runs are training in worker processes"
        proc.send_signal(signal.SIGKILL)  # no chance to clean up: only the kernel can end the workers
        proc.wait(timeout=10)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and any(_alive(pid) for pid in workers):
            time.sleep(0.2)
        assert not any(_alive(pid) for pid in workers)
    finally:
        if proc.poll() is None:
            proc.kill()
        for pid in workers:
            if _alive(pid):
                import os
                os.kill(pid, signal.SIGKILL)
