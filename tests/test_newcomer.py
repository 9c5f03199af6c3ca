"""What a newcomer meets first, on the real commands: `train` states its plan (the episode cap,
early stopping, the evaluation cadence) and announces the constant-action baseline; shipped
worlds are found by bare name by every command (an unknown one is one line naming where it
looked); recorded videos follow the drone at 10 frames per simulated second."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sitl_bridge.cli import main as cli
from sitl_bridge.data_paths import worlds_dir
from sitl_bridge.rl.learner.config import TrainConfig
from sitl_bridge.rl.training.train_plan import plan_lines

REPO = Path(__file__).resolve().parent.parent
TINY = ["--batch-size", "16", "--layers", "2", "--hidden-units", "16", "--no-progress"]


def sb(*argv: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-m", *argv], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=300)


def test_the_plan_says_the_cap_and_when_training_stops() -> None:
    early = "\n".join(plan_lines(TrainConfig(episodes=150, eval_every=10, eval_episodes=20, stop_on_success=0.9)))
    assert "at most 150 training episodes (--episodes is a cap)" in early
    assert "every 10 training episodes" in early and "stops early" in early and "90% success" in early
    plain = "\n".join(plan_lines(TrainConfig(episodes=50, eval_every=0, eval_episodes=5), done=20))
    assert "30 left after episode 20" in plain and "no early stopping" in plain and "trains all 50" in plain
    idle = "\n".join(plan_lines(TrainConfig(episodes=50, eval_every=0, stop_on_success=0.9)))
    assert "needs eval_every > 0" in idle


def test_train_help_calls_episodes_a_cap(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        cli(["train", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--episodes INT The most training episodes the run takes (a cap" in text


def test_train_by_bare_name_states_its_plan_and_announces_the_baseline(tmp_path: Path) -> None:
    """From a folder with no worlds/ in it: `train empty` finds the shipped world."""
    result = sb("sitl_bridge", "train", "empty", "--episodes", "2", "--eval-every", "1", "--eval-episodes", "2",
                "--stop-on-success", "0.9", "--out", str(tmp_path / "runs"), *TINY, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    lines = result.stderr.splitlines()
    first = next(i for i, line in enumerate(lines) if line.startswith("run directory:"))
    assert lines[first + 1].startswith("plan: at most 2 training episodes (--episodes is a cap)")
    assert any("stops early at the first periodic evaluation" in line for line in lines[first + 1:first + 5])
    baseline = [line for line in lines if line.startswith("measuring the constant-action baseline")]
    assert len(baseline) == 1 and "for 2 evaluation episodes (" in baseline[0]
    (run,) = (tmp_path / "runs").iterdir()
    assert json.loads((run / "run.json").read_text())["world"] == str(worlds_dir() / "empty.yaml")


@pytest.mark.parametrize("argv", [
    ("sitl_bridge", "worlds", "check", "{name}"),
    ("sitl_bridge.envs", "{name}"),
    ("sitl_bridge", "lr-probe", "{name}", "--batches", "1"),
    ("sitl_bridge", "train", "{name}", "--episodes", "0", "--out", "runs"),
])
def test_every_command_finds_a_shipped_world_by_bare_name(argv: tuple[str, ...], tmp_path: Path) -> None:
    found = sb(*[a.format(name="obstacle.yaml") for a in argv], cwd=tmp_path)
    if argv[1] != "lr-probe":  # lr-probe trains a while; the unknown name is what it must say at once
        assert found.returncode == 0, found.stderr
    missing = sb(*[a.format(name="nosuch_world") for a in argv], cwd=tmp_path)
    assert missing.returncode != 0
    error = missing.stderr.strip()
    assert "\n" not in error and "nosuch_world: cannot find world file (searched " in error
    assert str(worlds_dir()) in error


def test_eval_and_its_video_follow_the_drone_through_each_action(tmp_path: Path) -> None:
    pytest.importorskip("imageio_ffmpeg", reason="the `video` extra is not installed")
    import imageio.v3 as iio

    assert cli(["train", "obstacle", "--episodes", "1", "--eval-episodes", "0", "--out", str(tmp_path / "runs"),
                *TINY]) == 0
    (run,) = (tmp_path / "runs").iterdir()
    assert cli(["eval", str(run), "--world", "obstacle", "--episodes", "1", "--json",
                "--video", str(tmp_path / "vid")]) == 0
    (video,) = sorted((tmp_path / "vid").glob("*.mp4"))
    frames = iio.imread(video, plugin="FFMPEG")
    meta = iio.immeta(video, plugin="FFMPEG")
    from sitl_bridge.envs.scenario import load_scenario

    action = load_scenario(worlds_dir() / "obstacle.yaml").task.action
    per_action = round(action.duration_s / 0.1) + round(action.zero_velocity_s / 0.1)
    assert per_action >= 10 and frames.shape[0] > per_action
    assert (frames.shape[0] - 1) % per_action == 0  # the reset's frame, then one every 0.1 s of each action
    assert meta["fps"] == 10
    middle = frames[len(frames) // 2].astype(int)
    body = (middle[..., 0] > 150) & (middle[..., 1] > 90) & (middle[..., 1] < 200) & (middle[..., 2] < 80)
    rotors = middle.max(axis=2) < 60  # the dark discs over the rotors
    assert body.sum() > 100 and rotors.sum() > 100
    columns = np.flatnonzero((body | rotors).any(axis=0))
    assert columns[-1] - columns[0] >= 30, "the drone is not tens of pixels wide"
