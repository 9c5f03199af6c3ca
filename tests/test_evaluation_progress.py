"""The progress line of a greedy evaluation shows the success so far, as the result counts it."""

from __future__ import annotations

import re

import pytest

import sitl_bridge
from sitl_bridge.rl.common.drones_env import DronesEnv
from sitl_bridge.rl.evaluation.evaluate import evaluate_on


def test_the_last_progress_line_shows_the_whole_evaluations_success(capsys: pytest.CaptureFixture[str]) -> None:
    world = "worlds/random_obstacle.yaml"
    env = DronesEnv(sitl_bridge.make_env(world, autopilot="direct", seed=0))
    try:
        # "toward the goal" through randomly placed obstacles: some episodes reach it, some crash
        result, traces = evaluate_on(env, lambda obs: 6, world=world, episodes=6, progress=True)
    finally:
        env.close()
    outcomes = [t.outcome for t in traces]
    assert "goal" in outcomes and outcomes[-1] != "goal", outcomes  # mixed, and the last one failed
    shown = re.findall(r"success=(\d+)%", capsys.readouterr().err)
    assert shown and int(shown[-1]) == round(100 * result.success_rate), (shown, result.success_rate)
