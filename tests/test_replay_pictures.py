"""Pictures of behaviour (`sitl-bridge replay`, `rl/analysis/pictures.py`, `rl/analysis/reflight.py`) on a tiny real
run (direct backend): logged episodes fly again exactly, the trajectory is drawn where it flew in
both views, GIFs animate, greedy episodes are evaluation episodes, bad input is one line."""

from __future__ import annotations

import argparse
import importlib
import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from sitl_bridge.envs.scenario import load_scenario
from sitl_bridge.rl.analysis import pictures
from sitl_bridge.rl.analysis.pictures import (
    EpisodePicture,
    action_legend,
    draw_episode,
    draw_grid,
    run_lengths,
)
from sitl_bridge.rl.analysis.reflight import fly, greedy_pictures, refly_logged, typical
from sitl_bridge.rl.common.drones_env import DronesEnv, scenario_env_factory
from sitl_bridge.rl.common.episode_log import read_records
from sitl_bridge.rl.evaluation.rollout import eval_seeds

REPO = Path(__file__).resolve().parent.parent
OBSTACLE = str(REPO / "worlds" / "obstacle.yaml")
TINY = ["--batch-size", "16", "--layers", "2", "--hidden-units", "16", "--eval-every", "0",
        "--eval-episodes", "0", "--no-progress"]
DPI = 80


def cli(*argv: str) -> int:
    parser = argparse.ArgumentParser()
    subparsers = parser.add_subparsers()
    for name in ("train", "replay"):
        importlib.import_module(f"sitl_bridge.commands.{name}").register(subparsers)
    args = parser.parse_args(list(argv))
    return args.func(args)


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("runs")
    assert cli("train", OBSTACLE, "--episodes", "3", "--seed", "1", "--out", str(out), *TINY) == 0
    (folder,) = [p for p in out.iterdir() if p.is_dir()]
    return folder


@pytest.fixture(scope="module")
def flown(run: Path) -> list[EpisodePicture]:
    """Every logged episode of the run, flown again."""
    result = []
    for episode in range(3):
        picture, differences = refly_logged(run, episode)
        assert differences == [], differences
        result.append(picture)
    return result


def test_logged_episodes_fly_again_exactly(run: Path, flown: list[EpisodePicture]) -> None:
    records = read_records(run / "episodes.jsonl")
    for record, picture in zip(records, flown, strict=True):
        (trace,) = picture.traces
        assert trace.actions == record["actions"]
        assert trace.outcome == record["outcome"]
        assert trace.seed == record["env_seed"]
        assert trace.reward == pytest.approx(record["reward"], abs=1e-6)
        assert len(trace.positions_enu_m) == len(record["actions"]) + 1
        assert np.allclose(trace.positions_enu_m[-1], record["extra"]["position_enu_m"], atol=0.01)
        assert [o.name for o in picture.layout.obstacles] == ["block"]


def test_a_log_that_does_not_fly_again_is_warned_about(run: Path, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    copy = tmp_path / run.name
    shutil.copytree(run, copy, ignore=shutil.ignore_patterns("replay", "tb", "checkpoints"))
    lines = (copy / "episodes.jsonl").read_text().splitlines()
    first = json.loads(lines[0])
    first["actions"] = first["actions"][:-1] + [7 if first["actions"][-1] != 7 else 5]
    first["outcome"] = "goal" if first["outcome"] != "goal" else "timeout"
    (copy / "episodes.jsonl").write_text("\n".join([json.dumps(first), *lines[1:]]) + "\n")
    assert cli("replay", str(copy), "--episode", "0", "--out", str(tmp_path / "e0.png")) == 0
    err = capsys.readouterr().err
    assert err.startswith("warning: the re-flown episode 0 differs from the log (drone 0: outcome ")
    assert (tmp_path / "e0.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _pixels(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB"), dtype=int)


def _projected(picture: EpisodePicture) -> tuple[np.ndarray, np.ndarray, tuple, tuple]:
    """Pixel (column, row) of every trajectory point in the top and the side view of the PNG
    `draw_episode` writes at DPI, and both views' pixel boxes (same figure, built the same way)."""
    fig, top, side = pictures._episode_figure(picture)
    pictures._draw_views(top, side, picture, upto=None)
    fig.set_dpi(DPI)
    fig.canvas.draw()
    height = fig.canvas.get_width_height()[1]
    path = np.asarray(picture.traces[0].positions_enu_m)
    views = pictures._Views.of(picture)

    def pixels(ax, points) -> np.ndarray:  # noqa: ANN001
        xy = ax.transData.transform(points)
        return np.column_stack([xy[:, 0], height - xy[:, 1]])

    def box(ax) -> tuple:  # noqa: ANN001
        b = ax.get_window_extent()
        return b.x0, height - b.y1, b.x1, height - b.y0

    top_px = pixels(top, path[:, [views.along, views.across]])
    side_px = pixels(side, path[:, [views.along, 2]])
    return top_px, side_px, box(top), box(side)


def test_png_draws_the_trajectory_where_it_flew_in_both_views(flown: list[EpisodePicture],
                                                              tmp_path: Path) -> None:
    picture = max(flown, key=lambda p: p.traces[0].steps)  # the longest path
    with_path = draw_episode(picture.scenario, picture.layout, picture.traces, tmp_path / "with.png",
                             movers=picture.movers, title="t", dpi=DPI)
    blank = [replace(t, positions_enu_m=[]) for t in picture.traces]
    without = draw_episode(picture.scenario, picture.layout, blank, tmp_path / "without.png",
                           movers=picture.movers, title="t", dpi=DPI)
    a, b = _pixels(with_path), _pixels(without)
    assert a.shape == b.shape
    changed = np.abs(a - b).max(axis=2) > 40
    top_px, side_px, top_box, side_box = _projected(picture)
    rows, cols = np.nonzero(changed)
    for points, (x0, y0, x1, y1) in ((top_px, top_box), (side_px, side_box)):
        # every trajectory point is drawn: pixels changed right there
        for col, row in points:
            r, c = int(round(row)), int(round(col))
            assert changed[r - 3:r + 4, c - 3:c + 4].any(), (col, row)
        # and each view holds changed pixels of its own
        inside = (cols >= x0) & (cols <= x1) & (rows >= y0) & (rows <= y1)
        assert inside.sum() > 50
    # nothing changed far from the trajectory (action labels sit next to it)
    points = np.vstack([top_px, side_px])
    nearest = np.min(np.hypot(cols[:, None] - points[None, :, 0], rows[:, None] - points[None, :, 1]), axis=1)
    assert np.mean(nearest < 45) > 0.97


def test_gif_animates_step_by_step(flown: list[EpisodePicture], tmp_path: Path) -> None:
    picture = min(flown, key=lambda p: p.traces[0].steps)  # the shortest episode: a quick GIF
    out = draw_episode(picture.scenario, picture.layout, picture.traces, tmp_path / "e.gif", dpi=50, fps=5)
    gif = Image.open(out)
    assert gif.n_frames >= picture.traces[0].steps + 1 >= 3
    gif.seek(0)
    first = np.asarray(gif.convert("RGB"), dtype=int)
    gif.seek(gif.n_frames - 1)
    last = np.asarray(gif.convert("RGB"), dtype=int)
    assert (np.abs(first - last).max(axis=2) > 40).sum() > 20


def test_bad_input_is_one_line(run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for argv, says in ((["--episode", "99"], "no episode 99 in episodes.jsonl (it holds episodes 0..2)"),
                       (["--episode", "-1"], "episode numbers start at 0"),
                       (["--episode", "0", "--out", str(tmp_path / "x.jpg")], "expected a .png or .gif")):
        if "--out" not in argv:
            argv = [*argv, "--out", str(tmp_path / "x.png")]
        assert cli("replay", str(run), *argv) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and says in err and err.count("\n") == 1, err
    assert cli("replay", str(tmp_path), "--episode", "0", "--out", str(tmp_path / "x.png")) == 2
    assert "not a run directory" in capsys.readouterr().err
    assert not list(tmp_path.glob("x.*"))


def test_greedy_episodes_are_evaluation_episodes_and_make_a_grid(run: Path, tmp_path: Path) -> None:
    from sitl_bridge.rl.learner.policy import policy_from_checkpoint

    greedy = greedy_pictures(run, [0, 2], seed=4)
    seeds = eval_seeds(4, 3)
    assert [p.traces[0].seed for p in greedy] == [seeds[0], seeds[2]]
    policy = policy_from_checkpoint(run)
    env = DronesEnv(scenario_env_factory(OBSTACLE)(0))
    try:
        obs, _ = env.reset(seeds[2])
        assert greedy[1].traces[0].actions[0] == policy(obs[0])
    finally:
        env.close()
    chosen = typical(greedy, 4)
    assert 1 <= len(chosen) <= 2 and all(" of 2 episodes: " in title for _, title in chosen)
    grid = draw_grid([p for p, _ in chosen] * 2, tmp_path / "grid.png", [t for _, t in chosen] * 2,
                     columns=2, dpi=50)
    assert Image.open(grid).size[0] > Image.open(grid).size[1] / 3
    with pytest.raises(ValueError, match="titles"):
        draw_grid(greedy, tmp_path / "g.png", ["one"])


def test_movers_are_recorded_and_walls_drawn(tmp_path: Path) -> None:
    world = str(REPO / "worlds" / "street.yaml")
    scenario = load_scenario(world)
    env = DronesEnv(scenario_env_factory(world)(0))
    try:
        picture = fly(env, scenario, 3, lambda _d, step, _o: 6 if step < 3 else None, title="street")
    finally:
        env.close()
    (trace,) = picture.traces
    assert trace.actions == [6, 6, 6] and trace.outcome == "unfinished"
    assert {"pedestrian_1", "bird_1"} <= set(picture.movers)
    walk = np.asarray(picture.movers["pedestrian_1"])
    assert walk.shape == (4, 3) and np.linalg.norm(walk[-1] - walk[0]) > 1.0  # 1.4 m/s for 3 s
    out = draw_episode(scenario, picture.layout, picture.traces, tmp_path / "street.png",
                       movers=picture.movers, dpi=40)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_action_names_in_the_scenarios_frame() -> None:
    assert action_legend(load_scenario(OBSTACLE)).startswith("actions (world frame): 0 east, 1 west, 2 south, 3 north")
    relative = action_legend(load_scenario(REPO / "worlds" / "two_drones_empty_relative.yaml"))
    assert relative.startswith("actions (goal frame): 0 right, 1 left, 2 back, 3 forward")
    assert run_lengths([6, 6, 3, 7, 7, 7]) == [(0, 6, 2), (2, 3, 1), (3, 7, 3)]


def test_two_drone_episode_flies_again_with_both_drones(tmp_path: Path) -> None:
    world = str(REPO / "worlds" / "two_drones_empty_relative.yaml")
    assert cli("train", world, "--episodes", "1", "--seed", "2", "--out", str(tmp_path), *TINY) == 0
    (folder,) = [p for p in tmp_path.iterdir() if p.is_dir()]
    picture, differences = refly_logged(folder, 0)
    assert differences == []
    records = read_records(folder / "episodes.jsonl")
    assert [t.actions for t in picture.traces] == [r["actions"] for r in records]
    assert [t.drone for t in picture.traces] == [0, 1]
