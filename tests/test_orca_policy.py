"""The ORCA policy flown through the multi-drone env (`direct` backend) and by `sitl-bridge eval
--policy orca`: each drone decides from its own observation only."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sitl_bridge.cli import main as cli
from sitl_bridge.errors import ConfigError
from sitl_bridge.rl.analysis.orca_policy import choose_action, orca_policy
from sitl_bridge.rl.evaluation.evaluate import evaluate_in_world
from sitl_bridge.rl.evaluation.rollout import Trace
from sitl_bridge.rl.evaluation.separation import separation
from sitl_bridge.rl.experiments.seeds import EVAL_SEED_BASE

REPO = Path(__file__).resolve().parent.parent
TE = REPO / "worlds" / "two_drones_empty.yaml"


def test_a_head_on_pair_flying_orca_passes_apart_and_reaches_both_goals() -> None:
    result, traces = evaluate_in_world(orca_policy(TE), TE, episodes=3, seed=EVAL_SEED_BASE)
    assert result.success_rate == 1.0 and result.crash_rate == 0.0
    apart = separation(traces)
    assert apart.episodes == 3 and apart.lost == 0 and apart.least_m > 1.0
    for trace in traces:  # each sidestepped (a horizontal move across its path) before passing
        assert {0, 1} & set(trace.actions[:3])


def test_discrete_choice_sidesteps_where_orca_forbids_the_straight_line() -> None:
    from sitl_bridge.rl.analysis.orca import HalfPlane

    moves = np.array([[1, 0, 0], [-1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1], [0, 1, 0], [0, 0, 0]],
                     dtype=float)
    ahead_blocked = [HalfPlane(np.array([0.0, 0.8]), np.array([-1.0, 0.0]))]  # allowed: vy <= 0.8
    assert choose_action(np.array([0.0, 0.8, 0.0]), ahead_blocked, moves, 1.0) == 0  # right of north: east
    assert choose_action(np.array([0.0, 1.0, 0.0]), [], moves, 1.0) == 3  # nothing in the way: north
    assert choose_action(np.array([0.0, 0.2, 0.0]), ahead_blocked, moves, 1.0) == 7  # nearly stop: hover


def test_a_scenario_without_transponder_data_is_refused_in_one_line() -> None:
    with pytest.raises(ConfigError, match="needs position, velocity, own_id, transponder; missing"):
        orca_policy(REPO / "worlds" / "empty.yaml")


def test_an_encounter_world_on_world_frame_inputs_is_refused_in_one_line(tmp_path: Path) -> None:
    """Its goals and walls are drawn per episode; the world-frame policy's map is read once (the
    shipped encounter worlds observe agent-relative inputs: the travel-frame ORCA flies them)."""
    import yaml

    root = yaml.safe_load((REPO / "worlds" / "encounters.yaml").read_text())
    root["task"]["observation"] = ["position", "velocity", "own_id", "transponder", "goal_position"]
    path = tmp_path / "encounters_world_frame.yaml"
    path.write_text(yaml.safe_dump(root))
    with pytest.raises(ConfigError, match="world.encounter: the ORCA policy on world-frame observations flies "
                                          "fixed-geometry worlds only"):
        orca_policy(path)


def test_separation_counts_episodes_closer_than_a_metre() -> None:
    near = [Trace(0, 0, 1, positions_enu_m=[[0, 0, 2], [0, 1, 2]]), Trace(0, 1, 1, positions_enu_m=[[0, 3, 2], [0, 1.5, 2]])]
    far = [Trace(1, 0, 2, positions_enu_m=[[0, 0, 2]]), Trace(1, 1, 2, positions_enu_m=[[5, 0, 2]])]
    apart = separation(near + far)
    assert (apart.episodes, apart.lost, apart.least_m) == (2, 1, pytest.approx(0.5))


def test_eval_policy_orca_prints_success_and_separation(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli(["eval", "--policy", "orca", "--world", str(TE), "--episodes", "2", "--json"]) == 0
    captured = capsys.readouterr()
    result = json.loads(captured.out)
    assert result["success_rate"] == 1.0 and result["separation"]["lost"] == 0
    assert result["episode_seed"] == EVAL_SEED_BASE and "eval_seeds(1000000, 2)" in captured.err
    assert cli(["eval", "--policy", "orca", "--episodes", "1"]) == 2
    assert "needs --world" in capsys.readouterr().err


def test_a_move_into_a_wall_of_the_map_is_never_chosen() -> None:
    policy = orca_policy(REPO / "worlds" / "two_drones_window.yaml")
    layout = policy.layout
    obs = np.zeros(policy.scenario.task.observation_size)
    obs[layout["position"]] = [-3.0, -4.0, 5.0]  # 1 m inside the west wall of the south yard
    obs[layout["own_id"]] = 0
    obs[layout["goal_position"]] = [0.0, 4.0, 5.0]
    moves = policy.action_velocities(obs)
    clear = policy.clear_moves(obs, moves)
    assert not clear[1] and clear[0] and clear[7]  # west into the wall: no; east, hover: yes
    # ORCA's wish pointing west still flies a clear code
    wanted = np.array([-1.0, 0.0, 0.0])
    assert choose_action(wanted, [], moves, 1.0, clear) != 1
    assert choose_action(wanted, [], moves, 1.0) == 1
