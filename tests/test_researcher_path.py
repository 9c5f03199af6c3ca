"""A researcher's first hour, through the real `sitl-bridge` entry point in a temporary
directory other than the repository: validation of every section, self-contained run
directories with provenance, the run's own world by default, clear one-line errors."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from test_rl_helpers import corridor_factory, tiny_config

from sitl_bridge.rl.training.run_dir import RunSpec
from sitl_bridge.rl.training.trainer import Trainer

REPO = Path(__file__).resolve().parent.parent
WORLDS = REPO / "worlds"
TINY = ["--batch-size", "16", "--layers", "2", "--hidden-units", "16", "--eval-every", "0",
        "--eval-episodes", "2", "--no-progress"]


def sb(*args: str, cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sitl_bridge", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=timeout)


def edited(tmp_path: Path, source: str, name: str, edit) -> Path:
    data = yaml.safe_load((WORLDS / source).read_text())
    edit(data)
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return path


def _set(path: list, value):
    def edit(data: dict) -> None:
        node = data
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value
    return edit


def _rename(section: str, old: str, new: str):
    def edit(data: dict) -> None:
        data[section][new] = data[section].pop(old)
    return edit


def _obstacle_on_spawn(data: dict) -> None:
    data["world"]["obstacles"][0]["position"] = list(data["world"]["vehicles"][0]["spawn"]["position"])


def _cylinder_with_size(data: dict) -> None:
    data["world"]["obstacles"][0].update(shape="cylinder", radius=0.5, height=2.0)


def _swap_in_goal_frame(data: dict) -> None:
    data["task"]["action"].update(frame="goal", swap_drones=[1])


BROKEN = [
    ("obstacle.yaml", _rename("task", "max_steps", "max_stepz"), "task.max_stepz: unknown key"),
    ("obstacle.yaml", _set(["task", "action", "frame"], "goals"), "task.action.frame: expected one of"),
    ("obstacle.yaml", _rename("train", "gamma", "gamma_x"), "train.gamma_x: unknown key"),
    ("obstacle.yaml", _set(["world", "goals", 0, "center"], [100, 100, 2]),
     "world.goals[0].center: expected a goal box overlapping the workspace"),
    ("obstacle.yaml", _obstacle_on_spawn, "obstacle 'block' covers the spawn point"),
    ("obstacle.yaml", _cylinder_with_size, "world.obstacles[0].size: a cylinder has no `size`"),
    ("two_drones_empty.yaml", _swap_in_goal_frame, "task.action.swap_drones: expected [] with `frame: goal`"),
]


@pytest.mark.parametrize(("source", "edit", "message"), BROKEN, ids=[b[2][:30] for b in BROKEN])
def test_worlds_check_validates_every_section_and_the_geometry(tmp_path: Path, source, edit, message) -> None:
    path = edited(tmp_path, source, "broken.yaml", edit)
    result = sb("worlds", "check", str(path), cwd=tmp_path)
    assert result.returncode == 1
    assert message in result.stderr
    assert result.stderr.strip().count("\n") == 0, result.stderr  # one line


def test_train_refuses_a_broken_scenario_before_making_a_run_dir(tmp_path: Path) -> None:
    path = edited(tmp_path, "obstacle.yaml", "broken.yaml", _obstacle_on_spawn)
    result = sb("train", str(path), "--episodes", "1", "--out", "runs", *TINY, cwd=tmp_path)
    assert result.returncode == 2
    assert "covers the spawn point" in result.stderr
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").iterdir())


def test_a_run_directory_is_self_contained(tmp_path: Path) -> None:
    start = tmp_path / "start"
    start.mkdir()
    (start / "mine.yaml").write_text((WORLDS / "empty.yaml").read_text())
    result = sb("train", "mine.yaml", "--episodes", "1", "--out", "runs", *TINY, cwd=start)
    assert result.returncode == 0, result.stderr
    (run,) = (start / "runs").iterdir()
    (start / "mine.yaml").unlink()  # the original scenario is gone: the run must not need it
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()

    spec = json.loads((run / "run.json").read_text())
    assert spec["world"] == "mine.yaml"
    assert spec["created"].endswith("Z") and spec["created"][:2] == "20"
    assert spec["version"] and "train mine.yaml" in spec["command"] and "python" in spec["platform"]
    assert "git_commit" in spec
    assert (run / "scenario.yaml").read_text() == (WORLDS / "empty.yaml").read_text()

    for args in (["eval", str(run), "--episodes", "1"], ["rules", str(run), "--episodes", "1"],
                 ["plot", str(run)], ["train", "--resume", str(run), "--episodes", "2", "--no-progress"]):
        result = sb(*args, cwd=elsewhere)
        assert result.returncode == 0, (args, result.stderr)
    assert (run / "learning_curves.png").is_file()
    lines = (run / "episodes.jsonl").read_text().splitlines()
    assert [json.loads(line)["episode"] for line in lines] == [0, 1]


def test_resume_summary_separates_this_session_from_the_run(tmp_path: Path) -> None:
    result = sb("train", str(WORLDS / "empty.yaml"), "--episodes", "1", "--out", "runs", *TINY, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    (run,) = (tmp_path / "runs").iterdir()
    result = sb("train", "--resume", str(run), "--episodes", "2", "--no-progress", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "resuming after episode 1" in result.stderr
    assert "this session: 1 episodes" in result.stdout
    assert "run total: 2 of 2 episodes" in result.stdout


def test_plot_on_a_folder_that_is_not_a_run_is_one_line(tmp_path: Path) -> None:
    result = sb("plot", str(tmp_path), cwd=tmp_path)
    assert result.returncode == 2
    assert result.stderr.strip() == f"error: {tmp_path}: not a run directory (no run.json)"


def test_version() -> None:
    from sitl_bridge import __version__

    result = sb("--version", cwd=REPO)
    assert result.returncode == 0 and result.stdout.strip() == f"sitl-bridge {__version__}"


def test_scenario_a_constant_action_solves_is_never_called_solved(tmp_path: Path) -> None:
    # In the corridor, always "toward the goal" (6) wins every episode: a greedy evaluation at
    # 100 % does not beat it, so training does not stop early as "solved".
    config = tiny_config(episodes=4, eval_every=2, eval_episodes=4, stop_on_success=0.5)
    with Trainer.start(tmp_path, RunSpec(world="corridor.yaml"), config, corridor_factory(),
                       progress=False, warn=lambda _msg: None) as trainer:
        baseline = trainer.constant_baseline()
        assert baseline.action == 6 and baseline.success_rate == 1.0
        assert baseline.per_action[7] == 0.0  # hovering never reaches the goal
        trainer.train()
        assert not trainer.stopped_early and trainer.episode == 4
        assert json.loads((trainer.run_dir / "baseline.json").read_text())["action"] == 6
