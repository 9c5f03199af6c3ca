"""Episodes that start in the air on `direct` (placed hovering, no take-off flown) against the
take-off start (`task.start: {takeoff: true}`): same first observation and first steps within
the take-off's own tolerance, reproducible, and no take-off flown. Real pybullet and stub."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sitl_bridge.envs import make_env
from sitl_bridge.envs.backends.base import EPISODE_START
from sitl_bridge.envs.features import observation_layout
from sitl_bridge.errors import ConfigError

WORLDS = Path(__file__).resolve().parents[1] / "worlds"
ACTIONS = [3, 5, 5]  # the start of the thesis's O solution: north, up, up
TOLERANCE_M = 0.1  # the take-off's acceptance band and the direct/stub agreement


def scenario_with_start(tmp_path: Path, start: str) -> Path:
    """worlds/obstacle.yaml with `task.start` set to `start` (YAML flow text)."""
    text = (WORLDS / "obstacle.yaml").read_text()
    anchor = "  start_altitude_m: 2.5"
    assert anchor in text
    path = tmp_path / "obstacle_start.yaml"
    path.write_text(text.replace(anchor, f"{anchor}\n  start: {start}", 1))
    return path


def fly(env, seed: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """The first observation and the true positions after reset and after each of ACTIONS; the
    altitude above home that the autopilot believed at the start in `env.believed_altitude_m`."""
    obs, info = env.reset(seed=seed)
    autopilot = env.backend.autopilots[0]
    env.believed_altitude_m = autopilot.home.position_ned_m[2] - autopilot.estimate.position_ned_m[2]
    positions = [info["position_enu_m"]]
    for action in ACTIONS:
        _, _, terminated, truncated, info = env.step(action)
        assert not (terminated or truncated)
        positions.append(info["position_enu_m"])
    return obs, positions


@pytest.mark.parametrize("estimator", ["sensors", "ground_truth"])
def test_in_air_start_matches_the_take_off_start(tmp_path: Path, estimator: str) -> None:
    takeoff = make_env(scenario_with_start(tmp_path, "{takeoff: true}"), autopilot="direct", estimator=estimator)
    in_air = make_env(WORLDS / "obstacle.yaml", autopilot="direct", estimator=estimator)
    try:
        assert takeoff.backend.takeoff and not in_air.backend.takeoff
        obs_t, flown_t = fly(takeoff, seed=2)
        # where the take-off ended as its autopilot saw it (its acceptance test is on the estimate)
        believed_t = takeoff.believed_altitude_m
        error_t = believed_t - (flown_t[0][2] - 0.06)  # spawn: body centre 0.06 m above the ground
        obs_a, flown_a = fly(in_air, seed=2)
        start = in_air.scenario.task.start_altitude_m
        spawn = np.array([0.0, 0.0, 0.06])
        # placed at the start altitude (the truth), which the take-off reaches as it sees it
        assert np.linalg.norm(flown_a[0] - spawn - (0.0, 0.0, start)) < TOLERANCE_M
        assert abs(believed_t - start) < TOLERANCE_M
        # the take-off start's altitude, seen as its estimate saw it, is the in-air start's
        assert abs(flown_a[0][2] - (flown_t[0][2] + error_t)) < TOLERANCE_M, (flown_a[0], flown_t[0], error_t)
        assert np.linalg.norm(flown_a[0][:2] - flown_t[0][:2]) < TOLERANCE_M
        # first observation: everything but what depends on the height equal within the tolerance
        layout = observation_layout(in_air.scenario.task.observation)
        lidar = obs_a[layout["lidar"]], obs_t[layout["lidar"]]
        beside = slice(0, lidar[0].size - 6)  # horizontal and up rays (the last 6 look down)
        np.testing.assert_allclose(lidar[0][beside], lidar[1][beside], atol=TOLERANCE_M)
        np.testing.assert_allclose(obs_a[layout["goal_position"]], obs_t[layout["goal_position"]], atol=TOLERANCE_M)
        np.testing.assert_allclose(obs_a[layout["position"]][:2], obs_t[layout["position"]][:2], atol=TOLERANCE_M)
        # the first steps fly alike: the same displacements within the tolerance
        for step, (a, t) in enumerate(zip(flown_a, flown_t, strict=True)):
            assert np.linalg.norm((a - flown_a[0]) - (t - flown_t[0])) < TOLERANCE_M, (step, a, t)
    finally:
        takeoff.close()
        in_air.close()


@pytest.mark.parametrize("estimator", ["sensors", "ground_truth"])
def test_in_air_start_is_reproducible_and_flies_no_take_off(estimator: str) -> None:
    first = make_env(WORLDS / "obstacle.yaml", autopilot="direct", estimator=estimator)
    second = make_env(WORLDS / "obstacle.yaml", autopilot="direct", estimator=estimator)
    try:
        backend = first.backend
        before = backend.steps
        obs, flown = fly(first, seed=5)
        settle_steps = backend.steps_for(EPISODE_START.settle_s, exact=False)
        action_steps = backend.steps_for(first.scenario.task.action.duration_s) * len(ACTIONS)
        assert backend.steps - before == settle_steps + action_steps  # only the settle: no arming, no climb
        fly(first, seed=9)  # another episode between: the start must not depend on history
        again_obs, again = fly(first, seed=5)
        fresh_obs, fresh = fly(second, seed=5)
        for other_obs, other in ((again_obs, again), (fresh_obs, fresh)):
            np.testing.assert_array_equal(obs, other_obs)
            np.testing.assert_array_equal(np.array(flown), np.array(other))
    finally:
        first.close()
        second.close()


@pytest.mark.parametrize(("start", "message"), [("{takeoff: maybe}", "takeoff"), ("{climb: true}", "climb")])
def test_bad_start_options_are_refused(tmp_path: Path, start: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        make_env(scenario_with_start(tmp_path, start), autopilot="direct")
