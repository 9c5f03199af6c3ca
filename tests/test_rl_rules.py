"""Rule extraction and plotting helpers on hand-made traces and records."""

from __future__ import annotations

import numpy as np
import pytest

from sitl_bridge.rl.analysis.behaviour_summary import path_geometry, run_length, summarize_behaviour
from sitl_bridge.rl.analysis.plots import per_episode, rolling_mean
from sitl_bridge.rl.evaluation.rollout import Trace


def trace(actions: list[int], path: list[tuple[float, float, float]], goal=(0.0, 8.0, 2.5),
          outcome: str = "goal", drone: int = 0) -> Trace:
    return Trace(episode=0, drone=drone, seed=0, actions=actions, reward=1.0, outcome=outcome,
                 positions_enu_m=[list(p) for p in path], goal_enu_m=list(goal))


OVER = trace([3, 5, 5, 3, 3, 3, 3, 4, 4],  # the thesis's O behaviour, flown north over an obstacle
             [(0, 0, 2.5), (0, 1, 2.5), (0, 1, 3.5), (0, 1, 4.5), (0, 2, 4.5), (0, 4, 4.5), (0, 6, 4.5),
              (0, 8, 4.5), (0, 8, 3.5), (0, 8, 2.5)])
STRAIGHT = trace([6] * 8, [(0, y, 2.5) for y in range(9)])
LEFT = trace([1, 3, 3, 0], [(0, 0, 2.5), (-1.5, 0, 2.5), (-1.5, 4, 2.5), (-1.5, 8, 2.5), (0, 8, 2.5)])


def test_run_length() -> None:
    assert run_length([3, 5, 5, 3, 3, 3, 3, 4, 4]) == "3 5x2 3x4 4x2"
    assert run_length([]) == ""


def test_path_geometry_climb_and_side() -> None:
    assert path_geometry(OVER).climb_above_m == pytest.approx(2.0)
    assert path_geometry(STRAIGHT).lateral_m == pytest.approx(0.0)
    # Flying north, west is to the left (positive).
    assert path_geometry(LEFT).lateral_m == pytest.approx(1.5)


def test_summary_statements() -> None:
    over = summarize_behaviour("obstacle", 3, [OVER, OVER, OVER])
    assert over.climb_over_share == 1.0
    assert any(s.startswith("climbs over") for s in over.statements)
    assert over.top_sequences == [("3 5x2 3x4 4x2", 3)]

    straight = summarize_behaviour("random_goal", 2, [STRAIGHT, STRAIGHT])
    assert straight.statements[0] == "mostly action 6 (toward goal): 100% of all actions"
    assert "flies the straight start-goal line" in straight.statements[1]

    both = summarize_behaviour("head-on", 1, [LEFT, trace([0, 3, 3, 1], [(0, 0, 2.5), (1.5, 0, 2.5), (1.5, 8, 2.5)],
                                                          drone=1)])
    assert both.left_share == 0.5 and both.right_share == 0.5
    assert set(both.per_drone_action_share) == {0, 1}


def test_rolling_mean_ignores_missing_values() -> None:
    values = np.array([np.nan, np.nan, 2.0, 4.0, 6.0])
    result = rolling_mean(values, 2)
    assert np.isnan(result[0]) and np.isnan(result[1])
    assert result[2:].tolist() == [2.0, 3.0, 5.0]


def test_per_episode_averages_drones() -> None:
    records = [
        {"episode": 0, "drone": 0, "reward": 10.0, "outcome": "goal", "epsilon": 1.0, "mean_loss": None,
         "steps": 5, "wall_time_s": 0.1},
        {"episode": 0, "drone": 1, "reward": -10.0, "outcome": "crash", "epsilon": 1.0, "mean_loss": None,
         "steps": 3, "wall_time_s": 0.1},
    ]
    data = per_episode(records)
    assert data["reward"].tolist() == [0.0] and data["success"].tolist() == [0.5]
    assert data["crash"].tolist() == [0.5] and np.isnan(data["loss"][0])
