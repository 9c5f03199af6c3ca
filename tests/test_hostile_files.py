"""Hostile scenario files through the real entry point: each is a one-line
error naming the file (and key), nothing is written outside `--out`, and a failed start leaves
no run directory."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

WORLDS = Path(__file__).resolve().parent.parent / "worlds"


def sb(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sitl_bridge", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=120)


def scenario(tmp_path: Path, section: str, key: str, value) -> Path:
    data = yaml.safe_load((WORLDS / "obstacle.yaml").read_text())
    node = data[section]
    *parents, last = key.split(".")
    for part in parents:
        node = node[int(part)] if isinstance(node, list) else node[part]
    node[int(last) if isinstance(node, list) else last] = value
    path = tmp_path / "hostile.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def one_line_error(result: subprocess.CompletedProcess, expected: str) -> None:
    assert result.returncode != 0
    assert "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert expected in result.stderr, result.stderr


CASES = [
    ("train", "experiment", "../../../../escaped", "train.experiment: expected a name of letters"),
    ("train", "replay_capacity", 100_000_000_000, "train.replay_capacity: expected an integer in"),
    ("train", "hidden_units", 10_000_000, "train.hidden_units: expected an integer in [1, 8192]"),
    ("train", "learning_rate", float("inf"), "train.learning_rate: expected a finite number"),
    ("world", "obstacles.0.size", [1e308, 1.0, 1.0], "world.obstacles[0].size: expected 3 finite numbers"),
    ("world", "physics", {"gravity": 1e308}, "world.physics.gravity: expected"),
    ("world", "vehicles.0.lidar", {"range": 1e308}, "world.vehicles[0].lidar.range: expected"),
]


@pytest.mark.parametrize(("section", "key", "value", "expected"), CASES, ids=[c[1] for c in CASES])
def test_absurd_values_are_refused_before_a_run_starts(tmp_path: Path, section, key, value, expected) -> None:
    path = scenario(tmp_path, section, key, value)
    work = tmp_path / "work"
    work.mkdir()
    result = sb("train", str(path), "--episodes", "1", "--out", "runs", "--no-progress", cwd=work)
    one_line_error(result, expected)
    assert not (work / "runs").exists() or not any((work / "runs").iterdir())
    assert not list(tmp_path.parent.glob("escaped*")) and not list(work.parent.glob("escaped*"))


def test_non_utf8_file(tmp_path: Path) -> None:
    path = tmp_path / "latin1.yaml"
    path.write_bytes("world:\n  name: caf\xe9\n".encode("latin-1"))
    one_line_error(sb("worlds", "check", str(path), cwd=tmp_path), "not UTF-8 text")


def test_deeply_nested_file(tmp_path: Path) -> None:
    path = tmp_path / "nested.yaml"
    path.write_text("[" * 100_000)
    one_line_error(sb("worlds", "check", str(path), cwd=tmp_path), "levels deep")


def test_a_name_too_long_for_the_file_system(tmp_path: Path) -> None:
    name = "w" * 5000 + ".yaml"
    one_line_error(sb("worlds", "check", name, cwd=tmp_path), "cannot read file (File name too long)")
    one_line_error(sb("train", name, "--out", "runs", cwd=tmp_path), "File name too long")
    assert not (tmp_path / "runs").exists()
