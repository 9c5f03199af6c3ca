"""One observation for every drone count of the encounter family, policies flown by every drone
on its own observation (no shared state), ORCA and the thesis's rules 0-5 on encounter worlds, and
the per-encounter-type table re-derived from its per-episode records."""

from __future__ import annotations

import json
import math
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import yaml

from sitl_bridge.cli import main as cli
from sitl_bridge.envs import make_parallel_env
from sitl_bridge.envs.features import absent_far, parse_observation
from sitl_bridge.envs.view import DroneView, ScenarioLimits
from sitl_bridge.errors import Node
from sitl_bridge.rl.analysis.rule_policy import rule_policy

REPO = Path(__file__).resolve().parents[1]
WORLDS = REPO / "worlds"
THESIS_RULES = WORLDS / "rules" / "thesis_rules.yaml"
FAMILY = ("encounters", "encounters_converging", "encounters_heldout", "encounters_heldout_converging")


def _view(others: list[list[float]], position=(0.0, 0.0, 2.5)) -> DroneView:
    n = len(others)
    zero = np.zeros(3)
    return DroneView(index=0, position_enu_m=np.array(position), previous_position_enu_m=np.array(position),
                     euler_enu_rad=zero, velocity_enu_m_s=zero, start_enu_m=np.array([0.0, -4.0, 0.0]),
                     goal_enu_m=np.array([0.0, 4.0, 2.5]), lidar={}, priority=1.0, other_priorities=np.zeros(n),
                     others_position_enu_m=np.array(others, dtype=float).reshape(-1, 3),
                     others_velocity_enu_m_s=np.zeros((n, 3)))


def _travel_others(options: dict | None, drones: int):
    limits = ScenarioLimits(drones, np.array([-8.0, -8.0, 0.0]), np.array([8.0, 8.0, 6.0]))
    item = "travel_others" if options is None else {"travel_others": options}
    return parse_observation(Node([item], "test", "observation"), limits)[0], limits


def test_travel_others_slots_hold_the_nearest_first_and_pad_absent_drones_far_behind() -> None:
    feature, limits = _travel_others({"count": 3, "order": "nearest", "absent": "far"}, drones=2)
    value = feature(_view([[0.0, 3.0, 2.5]]))  # one other drone, 3 m north = ahead (travel north)
    rows = value.reshape(3, 6)
    assert rows[0] == pytest.approx([0.0, 3.0, 0.0, 0.0, 0.0, 0.0])
    assert rows[1] == pytest.approx(absent_far(limits.diagonal_m)) and rows[2] == pytest.approx(rows[1])
    assert rows[1][1] == pytest.approx(-limits.diagonal_m)  # as far behind as any drone can be
    feature, _ = _travel_others({"count": 3, "order": "nearest", "absent": "far"}, drones=4)
    rows = feature(_view([[5.0, 0.0, 2.5], [0.0, 1.0, 2.5], [-2.0, 0.0, 2.5]])).reshape(3, 6)
    assert [float(np.linalg.norm(r[:3])) for r in rows] == pytest.approx([1.0, 2.0, 5.0])  # nearest first
    assert rows[0][:2] == pytest.approx([0.0, 1.0]) and rows[1][:2] == pytest.approx([-2.0, 0.0])
    # the defaults are unchanged: drone order, zeros for an empty slot
    feature, _ = _travel_others({"count": 2}, drones=2)
    assert feature(_view([[0.0, 3.0, 2.5]])).reshape(2, 6)[1] == pytest.approx(np.zeros(6))


def test_a_bad_travel_others_option_is_a_one_line_error() -> None:
    from sitl_bridge.errors import ConfigError

    with pytest.raises(ConfigError, match=r"observation\[0\]\.travel_others\.order.*nearest"):
        _travel_others({"count": 3, "order": "closest"}, drones=2)


def test_one_task_gives_one_observation_space_for_two_and_four_drones() -> None:
    """Every file of the family declares the same task; a two-drone and a four-drone episode see
    the same space, the two-drone one with its empty slots padded far behind."""
    tasks = {name: yaml.safe_load((WORLDS / f"{name}.yaml").read_text())["task"] for name in FAMILY}
    assert all(task == tasks["encounters"] for task in tasks.values())
    two = make_parallel_env(WORLDS / "encounters.yaml", seed=0)
    four = make_parallel_env(WORLDS / "encounters_heldout_converging.yaml", seed=0)
    try:
        assert len(two.possible_agents) == 2 and len(four.possible_agents) == 4
        a, b = two.observation_space("drone0"), four.observation_space("drone3")
        assert a.shape == b.shape == (60,) and np.array_equal(a.low, b.low) and np.array_equal(a.high, b.high)
        obs2, _ = two.reset(seed=5)
        obs4, _ = four.reset(seed=5)
        layout = slice(6, 24)
        far = absent_far(two.scenario.task.observation[2].high[1])
        for agent, value in obs2.items():
            rows = value[layout].reshape(3, 6)
            assert rows[0][1] > -15.0 and np.allclose(rows[1:], far, atol=1e-4)
            assert two.observation_space(agent).contains(value)
        for agent, value in obs4.items():
            rows = value[layout].reshape(3, 6)
            distances = np.linalg.norm(rows[:, :3], axis=1)
            assert np.all(distances < 15.0) and np.all(np.diff(distances) >= -1e-5)
            assert four.observation_space(agent).contains(value)
    finally:
        two.close()
        four.close()


@pytest.mark.parametrize("family", ["encounters", "encounters_heldout_converging"])
def test_gymnasium_check_env_passes_with_two_and_four_drones(family: str) -> None:
    """The single-agent env (drone0 learning among the others) has the same 60 inputs too; the
    PettingZoo API test runs on both files in tests/test_encounters.py."""
    from gymnasium.utils.env_checker import check_env

    from sitl_bridge.envs import make_env

    env = make_env(WORLDS / f"{family}.yaml", seed=0)
    try:
        check_env(env, skip_render_check=True)
        assert env.observation_space.shape == (60,)
    finally:
        env.close()


def _converging_env(seed: int):
    env = make_parallel_env(WORLDS / "encounters_converging.yaml", seed=0)
    obs, infos = env.reset(seed=seed)
    return env, obs, infos


def test_a_rule_set_flown_by_three_drones_shares_no_state() -> None:
    """Each drone's action is the rule set's answer to its own observation alone: another drone's
    private state (its goal) changes nothing a drone sees or does, while the other drone's moves,
    which its transponder reports, do change what it sees."""
    policy = rule_policy(THESIS_RULES, WORLDS / "encounters_converging.yaml")
    a, obs_a, _ = _converging_env(11)
    b, obs_b, _ = _converging_env(11)
    try:
        assert sorted(obs_a) == ["drone0", "drone1", "drone2"]
        # drone1's goal is private: moved 3 m in env b, it hovers in both (its position unchanged)
        b.runner._goals[1] = b.runner._goals[1] + np.array([3.0, -3.0, 0.0])
        for _ in range(4):
            chosen = {agent: policy(obs_a[agent]) for agent in ("drone0", "drone2")}
            obs_a, *_ = a.step({**chosen, "drone1": 7})
            obs_b, *_ = b.step({**chosen, "drone1": 7})
            for agent in ("drone0", "drone2"):
                assert np.array_equal(obs_a[agent], obs_b[agent])
                assert policy(obs_a[agent]) == policy(obs_b[agent])
            assert not np.array_equal(obs_a["drone1"], obs_b["drone1"])  # its own goal offset differs
        # the same observation gives the same action whatever the others saw or were asked first
        mine = obs_a["drone0"]
        first = policy(mine)
        for other in ("drone1", "drone2"):
            policy(obs_b[other] + np.float32(0.5))
            assert policy(mine) == first
        # a move of drone1 (its transponder data) does reach the others' observations
        before = {agent: obs_a[agent].copy() for agent in ("drone0", "drone2")}
        obs_a, *_ = a.step({"drone0": 7, "drone1": 3, "drone2": 7})
        obs_b, *_ = b.step({"drone0": 7, "drone1": 7, "drone2": 7})
        assert any(not np.allclose(obs_a[agent][6:24], obs_b[agent][6:24], atol=0.05) for agent in before)
    finally:
        a.close()
        b.close()


def _wilson(k: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return centre - half, centre + half


def test_orca_and_the_thesis_rules_per_encounter_type_rederived_from_the_episode_records(tmp_path: Path,
                                                                                         capsys) -> None:
    out = tmp_path / "table.json"
    code = cli(["eval-encounters", "--world", "encounters", "--per-type", "3", "--orca", "--rules", str(THESIS_RULES),
                "--json", str(out)])
    assert code == 0
    printed = capsys.readouterr()
    assert "eval_seeds(3000000, ...), the verification set" in printed.err
    report = json.loads(out.read_text())
    labels = {"head_on", "crossing", "overtaking", "bottleneck", "head_on, late entry"}
    episodes = report["episodes"]
    groups: dict[tuple[str, str], list[dict]] = defaultdict(list)
    for record in episodes:
        groups[(record["encounter"], record["policy"])].append(record)
    assert {e for e, _ in groups} == labels and {p for _, p in groups} == {"ORCA", "rules: thesis rules 0-5"}
    assert all(len(group) == 3 for group in groups.values())
    # both policies flew the very same episodes
    seeds = {policy: sorted(r["seed"] for r in episodes if r["policy"] == policy) for policy in ("ORCA",)}
    assert seeds["ORCA"] == sorted(r["seed"] for r in episodes if r["policy"] == "rules: thesis rules 0-5")
    assert len(report["rows"]) == 10
    for row in report["rows"]:
        group = groups[(row["encounter"], row["policy"])]
        assert row["episodes"] == len(group) == 3
        for key, flag in (("success", lambda r: r["reached"] == r["drones"]),
                          ("collision", lambda r: r["crashed"] > 0),
                          ("lost_separation", lambda r: r["least_distance_m"] is not None
                           and r["least_distance_m"] < 1.0)):
            k = sum(1 for r in group if flag(r))
            assert row[key]["count"] == k and row[key]["rate"] == pytest.approx(k / 3)
            assert row[key]["ci95"] == pytest.approx(list(_wilson(k, 3)), abs=1e-9)
        times = [t for r in group for t in r["times_to_goal_s"]]
        paths = [d for r in group for d in r["path_lengths_m"]]
        assert row["time_to_goal_s"]["n"] == len(times) and row["path_length_m"]["n"] == len(paths)
        if times:
            assert row["time_to_goal_s"]["mean"] == pytest.approx(sum(times) / len(times))
            assert row["path_length_m"]["mean"] == pytest.approx(sum(paths) / len(paths))
            assert all(p >= 1.0 for p in paths) and all(t == int(t) and t >= 1 for t in times)
        line = f"| encounters | {row['encounter']} | {row['policy']} | 3 | "
        assert line in printed.out
    # what every measured run since shows: ORCA passes every head-on and keeps its distance
    head_on = groups[("head_on", "ORCA")]
    assert all(r["reached"] == 2 and r["crashed"] == 0 and r["least_distance_m"] > 1.0 for r in head_on)
    assert all(r["reached"] == 2 for r in groups[("head_on", "rules: thesis rules 0-5")])


def test_orca_flies_three_drones_converging_each_on_its_own_observation() -> None:
    from sitl_bridge.rl.analysis.orca_policy import orca_policy
    from sitl_bridge.rl.analysis.orca_travel import TravelOrcaPolicy
    from sitl_bridge.rl.common.drones_env import DronesEnv, scenario_env_factory
    from sitl_bridge.rl.evaluation.encounter_table import encounter_labels, fly_per_type
    from sitl_bridge.world import load_world

    world = WORLDS / "encounters_converging.yaml"
    policy = orca_policy(world)
    assert isinstance(policy, TravelOrcaPolicy)
    env = DronesEnv(scenario_env_factory(world)(0))
    try:
        records = fly_per_type(env, policy, policy_name="ORCA", world="encounters_converging",
                               labels=encounter_labels(load_world(world)), per_type=2, seed=3_000_000,
                               action_duration_s=1.0)
    finally:
        env.close()
    assert sorted({r.encounter for r in records}) == ["bottleneck", "converging", "converging, late entry"]
    assert all(r.drones == 3 for r in records)
    converging = [r for r in records if r.encounter.startswith("converging")]
    assert not any(r.collision for r in converging)  # ORCA keeps three converging drones apart


def test_eval_encounters_refuses_a_world_without_encounters_and_a_call_without_policy(capsys) -> None:
    assert cli(["eval-encounters", "--world", "two_drones_empty", "--per-type", "1", "--orca"]) == 2
    assert "no world.encounter: a per-type evaluation needs an encounter family" in capsys.readouterr().err
    assert cli(["eval-encounters", "--world", "encounters", "--per-type", "1"]) == 2
    assert "name at least one policy" in capsys.readouterr().err


def test_a_network_trained_on_two_drones_flies_four_in_the_per_type_table(tmp_path: Path, capsys) -> None:
    """One network for the family: trained (briefly) on the two-drone file, flown per type on the
    four-drone held-out file; a network of another input size is a one-line error."""
    out = tmp_path / "runs"
    assert cli(["train", str(WORLDS / "encounters.yaml"), "--episodes", "2", "--out", str(out), "--batch-size", "16",
                "--layers", "2", "--hidden-units", "16", "--eval-every", "0", "--eval-episodes", "1",
                "--no-progress"]) == 0
    (run,) = [p for p in out.iterdir() if p.is_dir()]
    table = tmp_path / "table.json"
    assert cli(["eval-encounters", "--world", "encounters_heldout_converging", "--per-type", "1",
                "--checkpoint", str(run), "--json", str(table)]) == 0
    report = json.loads(table.read_text())
    assert {r["encounter"] for r in report["rows"]} == {"bottleneck", "converging", "converging, late entry"}
    assert all(r["drones"] == 4 for r in report["episodes"])
    capsys.readouterr()
    small = REPO / "worlds" / "two_drones_empty_relative.yaml"
    assert cli(["train", str(small), "--episodes", "1", "--out", str(tmp_path / "small"), "--batch-size", "16",
                "--layers", "2", "--hidden-units", "16", "--eval-every", "0", "--eval-episodes", "1",
                "--no-progress"]) == 0
    (small_run,) = list((tmp_path / "small").iterdir())
    assert cli(["eval-encounters", "--world", "encounters", "--per-type", "1", "--checkpoint", str(small_run)]) == 2
    assert "the policy takes 13 observation values, got 60" in capsys.readouterr().err
