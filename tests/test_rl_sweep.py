"""`sitl-bridge sweep`: parallel runs with their own run dirs and a summary, resume of a
half-finished sweep, a failing run reported without stopping the others, the same through Ray."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from sitl_bridge.data_paths import worlds_dir

WORLD = str(worlds_dir() / "empty.yaml")
TINY = ["--episodes", "2", "--eval-every", "0", "--eval-episodes", "0"]


def _sweep(root: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sitl_bridge", "sweep", WORLD, "--out", str(root), *TINY, *extra],
                          capture_output=True, text=True, timeout=300)


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
    from sitl_bridge.rl.config import load_train_config
    from sitl_bridge.rl.drones_env import scenario_env_factory
    from sitl_bridge.rl.run_dir import RunSpec
    from sitl_bridge.rl.trainer import Trainer

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
    pytest.importorskip("ray")
    root = tmp_path / "sweep"
    proc = _sweep(root, "--seeds", "0-1", "--backend", "ray")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    rows = _summary(root)
    for seed in (0, 1):
        assert rows[seed]["status"] == "done"
        assert Path(rows[seed]["run_dir"]).parent == root / "base" / f"seed{seed}"
        assert _episodes(rows[seed]["run_dir"]) == 2
