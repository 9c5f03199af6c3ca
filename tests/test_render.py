"""Seeing the flight: rgb_array frames, recorded videos, and the GUI on a real
(virtual) display."""

from __future__ import annotations

import dataclasses
import os
import shutil
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import sitl_bridge.envs  # noqa: F401  (registers the ids)
from sitl_bridge import make_env, make_parallel_env
from sitl_bridge.envs.scenario import Scenario, load_scenario
from sitl_bridge.envs.single import SitlEnv

REPO = Path(__file__).resolve().parent.parent
WORLDS = REPO / "worlds"


def _scene_camera(path: Path) -> Scenario:
    """The scenario with the fixed camera over the whole workspace (the default follows the drone)."""
    scenario = load_scenario(path)
    render = dataclasses.replace(scenario.task.render, camera="scene")
    return dataclasses.replace(scenario, task=dataclasses.replace(scenario.task, render=render))


def test_rgb_array_frame_has_the_configured_shape_and_changes_where_the_drone_moves() -> None:
    env = SitlEnv(_scene_camera(WORLDS / "obstacle.yaml"), render_mode="rgb_array", seed=0, estimator="ground_truth")
    try:
        assert env.metadata["render_modes"] == ["rgb_array", "rgb_array_list", "human"]
        assert env.render_mode == "rgb_array"
        env.reset(seed=0)
        before = env.render()
        config = env.scenario.task.render
        assert before.shape == (config.height, config.width, 3) and before.dtype == np.uint8
        assert before.std() > 5  # drawn content, not a blank image
        for action in (5, 5, 5):  # up 3 m
            env.step(action)
        after = env.render()
        changed = np.any(before != after, axis=2)
        assert changed.sum() > 50, "the drone's move changed nothing in the picture"
        rows, cols = np.nonzero(changed)
        # the change is local (the drone), not the whole picture (camera fixed in scene mode)
        assert changed.mean() < 0.05 and rows.max() - rows.min() < config.height // 2
    finally:
        env.close()


def test_rendering_off_adds_nothing_to_the_simulation() -> None:
    plain = make_env(WORLDS / "obstacle.yaml", seed=0)
    drawn = make_env(WORLDS / "obstacle.yaml", seed=0, render_mode="rgb_array")
    filmed = make_env(WORLDS / "obstacle.yaml", seed=0, render_mode="rgb_array_list")
    try:
        assert plain.render() is None
        assert not plain.backend.sim.visual and drawn.backend.sim.visual
        plain.reset(seed=3)
        drawn.reset(seed=3)
        filmed.reset(seed=3)
        drawn.render()  # markers are visual only: they change nothing of the flight
        assert len(filmed.render()) == 1  # the reset's frame
        for action in (3, 3, 6):
            a = plain.step(action)
            b = drawn.step(action)
            c = filmed.step(action)  # flown in 0.1 s slices, a frame after each: the same flight
            np.testing.assert_allclose(a[0], b[0], atol=1e-6)
            np.testing.assert_array_equal(a[0], c[0])
            assert len(filmed.render()) == round(filmed.scenario.task.action.duration_s / 0.1)
    finally:
        plain.close()
        drawn.close()
        filmed.close()


def test_parallel_env_renders_the_whole_scenario() -> None:
    env = make_parallel_env(WORLDS / "two_drones_window.yaml", render_mode="rgb_array", seed=0)
    try:
        env.reset(seed=0)
        frame = env.render()
        assert frame.shape[2] == 3 and frame.std() > 5
    finally:
        env.close()


def test_record_video_writes_playable_files(tmp_path: Path) -> None:
    pytest.importorskip("moviepy", reason="moviepy (in the `test` extra) is not installed")
    import imageio.v3 as iio

    env = gym.make("sitl_bridge/Empty-v0", render_mode="rgb_array", estimator="ground_truth")
    env = gym.wrappers.RecordVideo(env, str(tmp_path / "videos"), episode_trigger=lambda _e: True, disable_logger=True)
    steps = []
    try:
        for episode in range(3):
            env.reset(seed=episode)
            count, done = 0, False
            while not done and count < 4:
                _, _, terminated, truncated, _ = env.step(6)
                count += 1
                done = terminated or truncated
            steps.append(count)
    finally:
        env.close()
    videos = sorted((tmp_path / "videos").glob("*.mp4"))
    assert len(videos) == 3
    for video, count in zip(videos, steps, strict=True):
        frames = iio.imread(video, plugin="FFMPEG")
        assert frames.shape[0] == count + 1  # the reset frame and one per step
        assert frames.shape[-1] == 3


def test_eval_video_records_each_episode(tmp_path: Path) -> None:
    pytest.importorskip("imageio_ffmpeg", reason="the `video` extra is not installed")
    import imageio.v3 as iio

    out = tmp_path / "runs"
    run = [sys.executable, "-m", "sitl_bridge"]
    tiny = ["--batch-size", "16", "--layers", "2", "--hidden-units", "16", "--eval-episodes", "0", "--no-progress"]
    assert subprocess.run([*run, "train", str(WORLDS / "empty.yaml"), "--episodes", "1", "--out", str(out), *tiny],
                          capture_output=True, timeout=300).returncode == 0
    (run_dir,) = out.iterdir()
    result = subprocess.run([*run, "eval", str(run_dir), "--episodes", "2", "--video", str(tmp_path / "vid")],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    videos = sorted((tmp_path / "vid").glob("episode_*.mp4"))
    assert [v.name for v in videos] == ["episode_0000.mp4", "episode_0001.mp4"]
    assert iio.imread(videos[0], plugin="FFMPEG").shape[0] >= 2


@pytest.mark.skipif(shutil.which("Xvfb") is None, reason="Xvfb not installed (apt-get install xvfb)")
def test_gui_under_xvfb_draws_the_scene(tmp_path: Path) -> None:
    script = tmp_path / "gui.py"
    script.write_text(
        "import numpy as np, pybullet as p, sys\n"
        "from sitl_bridge import make_env\n"
        f"env = make_env({str(WORLDS / 'obstacle.yaml')!r}, render_mode='human', estimator='ground_truth')\n"
        "env.reset(seed=0)\n"
        "env.step(5)\n"
        "cid = env.backend.sim.client_id\n"
        "assert p.getConnectionInfo(cid)['connectionMethod'] == p.GUI\n"
        "w, h, rgba, _, _ = p.getCameraImage(320, 240, renderer=p.ER_BULLET_HARDWARE_OPENGL, physicsClientId=cid)\n"
        "shot = np.asarray(rgba, dtype=np.uint8).reshape(h, w, 4)[:, :, :3]\n"
        "np.save(sys.argv[1], shot)\n"
        "env.close()\n")
    display = f":{90 + os.getpid() % 100}"
    xvfb = subprocess.Popen(["Xvfb", display, "-screen", "0", "1024x768x24", "-nolisten", "tcp"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        result = subprocess.run([sys.executable, str(script), str(tmp_path / "shot.npy")],
                                env={**os.environ, "DISPLAY": display}, capture_output=True, text=True,
                                timeout=240)
        assert result.returncode == 0, result.stderr[-2000:]
        shot = np.load(tmp_path / "shot.npy")
        assert shot.shape == (240, 320, 3)
        assert len(np.unique(shot.reshape(-1, 3), axis=0)) > 10  # not uniform: a drawn scene
    finally:
        xvfb.terminate()
        xvfb.wait(timeout=30)


def test_lidar_rays_are_drawn_when_asked(tmp_path: Path) -> None:
    import yaml

    data = yaml.safe_load((WORLDS / "obstacle.yaml").read_text())
    data["task"]["render"] = {"camera": "follow", "distance_m": 4.0, "lidar_rays": True, "width": 256, "height": 192}
    path = tmp_path / "rays.yaml"
    path.write_text(yaml.safe_dump(data))
    env = make_env(path, render_mode="rgb_array", seed=0, estimator="ground_truth")
    try:
        env.reset(seed=0)
        frame = env.render()
        assert frame.shape == (192, 256, 3)
        ray_pixels = np.all(frame == np.array([255, 200, 0], dtype=np.uint8), axis=2)
        assert ray_pixels.sum() > 100
    finally:
        env.close()


def test_run_policy_records_a_video_through_the_stub(tmp_path: Path, free_instance: int) -> None:
    pytest.importorskip("imageio_ffmpeg", reason="the `video` extra is not installed")
    import imageio.v3 as iio

    run = [sys.executable, "-m", "sitl_bridge"]
    tiny = ["--batch-size", "16", "--layers", "2", "--hidden-units", "16", "--eval-episodes", "0", "--no-progress"]
    out = tmp_path / "runs"
    assert subprocess.run([*run, "train", str(WORLDS / "empty.yaml"), "--episodes", "1", "--out", str(out), *tiny],
                          capture_output=True, timeout=300).returncode == 0
    (run_dir,) = out.iterdir()
    video = tmp_path / "flight.mp4"
    result = subprocess.run([*run, "run", "--policy", str(run_dir), "--speed-factor", "0", "--instance-base",
                             str(free_instance), "--video", str(video)], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert f"video: {video}" in result.stdout
    frames = iio.imread(video, plugin="FFMPEG")
    assert frames.shape[0] >= 2 and frames.shape[-1] == 3


def test_vector_env_renders_each_copy() -> None:
    from sitl_bridge import make_vec_env

    envs = make_vec_env(WORLDS / "empty.yaml", num_envs=2, render_mode="rgb_array", estimator="ground_truth")
    try:
        envs.reset(seed=0)
        frames = envs.render()
        assert len(frames) == 2 and all(f.shape == (384, 512, 3) for f in frames)
    finally:
        envs.close()
