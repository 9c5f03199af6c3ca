"""Behaviour classification and candidate rules on synthetic traces with known trajectories
(pass right, hover then go while another passes, back off, climb over, oscillation, direct)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sitl_bridge.envs.features import travel_frame
from sitl_bridge.envs.scenario import load_scenario
from sitl_bridge.errors import load_yaml
from sitl_bridge.rl.analysis.behaviour import (
    BehaviourAnalysis,
    RunBehaviour,
    classify,
    classify_episode,
    openings,
)
from sitl_bridge.rl.analysis.behaviour_summary import summarize_behaviour
from sitl_bridge.rl.analysis.candidate_rules import (
    _lidar_condition,
    candidate_rules,
    fidelity,
    rules_document,
    scenario_facts,
    thesis_checks,
    write_rules_yaml,
)
from sitl_bridge.rl.analysis.rule_policy import evaluate_rules
from sitl_bridge.rl.common.action_names import ACTION_NAMES_BY_FRAME, action_code, action_name
from sitl_bridge.rl.evaluation.rollout import Trace

WORLDS = Path(__file__).resolve().parent.parent / "worlds"
Z = 2.5


def trace(path: list[tuple[float, float]], goal: tuple[float, float], actions: list[int], *, drone: int = 0,
          episode: int = 0, outcome: str = "goal", z: list[float] | None = None) -> Trace:
    heights = z or [Z] * len(path)
    assert len(actions) == len(path) - 1
    return Trace(episode=episode, drone=drone, seed=100 + episode, actions=actions, outcome=outcome,
                 positions_enu_m=[[x, y, h] for (x, y), h in zip(path, heights, strict=True)],
                 goal_enu_m=[goal[0], goal[1], Z])


def line(x: float, ys: list[float]) -> list[tuple[float, float]]:
    return [(x, y) for y in ys]


def head_on(episode: int, side: str) -> list[Trace]:
    """Two drones 8 m apart on a head-on course, both sidestepping 1 m to their `side`."""
    s = 1.0 if side == "right" else -1.0  # drone 0 flies north: its right is east (+x)
    north = [(0, 0), (0, 1), (0, 2), (s, 2), (s, 3), (s, 4), (s, 5), (s, 6), (0, 6), (0, 7), (0, 8)]
    south = [(-x, 8 - y) for x, y in north]  # drone 1 flies south: its right is west
    side_code = 0 if side == "right" else 1   # goal frame: 0 right, 1 left
    back_code = 1 - side_code
    actions = [3, 3, side_code, 3, 3, 3, 3, back_code, 3, 3]
    return [trace(north, (0, 8), actions, drone=0, episode=episode),
            trace(south, (0, 0), actions, drone=1, episode=episode)]


def hover_then_go(episode: int = 0) -> list[Trace]:
    """Drone 0 (starts further south: lower priority) hovers 4 s while drone 1 passes 1 m east of it."""
    waiting = line(0, [0, 0, 0, 0, 0, 1, 2, 3, 4, 5, 6])
    passing = line(1, [5, 4, 3, 2, 1, 0, -1])
    return [trace(waiting, (0, 6), [7, 7, 7, 7, 3, 3, 3, 3, 3, 3], drone=0, episode=episode),
            trace(passing, (1, -1), [3] * 6, drone=1, episode=episode)]


def back_off(episode: int = 0) -> list[Trace]:
    """Drone 0 moves back 2 m while drone 1 approaches and passes, then goes."""
    backing = line(0, [0, -1, -2, -1, 0, 1, 2, 3, 4, 5, 6])
    passing = line(1, [5, 4, 3, 2, 1, 0, -1])
    return [trace(backing, (0, 6), [2, 2, 3, 3, 3, 3, 3, 3, 3, 3], drone=0, episode=episode),
            trace(passing, (1, -1), [3] * 6, drone=1, episode=episode)]


CLIMB = trace(line(0, [0, 1, 1, 1, 2, 3, 4, 5, 5, 5]), (0, 5), [3, 5, 5, 3, 3, 3, 3, 4, 4],
              z=[2.5, 2.5, 3.5, 4.5, 4.5, 4.5, 4.5, 4.5, 3.5, 2.5])
DIRECT = trace(line(0, [0, 1, 2, 3, 4, 5, 6, 7, 8]), (0, 8), [6] * 8)
OSCILLATING = trace(line(0, [0, 1, 0, 1, 0, 1, 0, 1]), (0, 8), [3, 2, 3, 2, 3, 2, 3], outcome="timeout")


def one(traces: list[Trace] | Trace, **kwargs) -> list:  # noqa: ANN003
    return classify_episode(traces if isinstance(traces, list) else [traces], **kwargs).drones


def test_action_names_follow_the_frame() -> None:
    assert action_name(3, "world") == "north" and action_name(3, "goal") == "forward"
    assert action_name(0, "goal") == "right" and action_name(9) == "9"
    assert all(action_code(action_name(c, f), f) == c for f in ACTION_NAMES_BY_FRAME for c in range(8))
    with pytest.raises(ValueError, match="forward"):
        action_code("north", "goal")
    # The old rules output named a goal-frame drone's action 3 "north".
    summary = summarize_behaviour("te", 1, head_on(0, "right"), frame="goal")
    assert "3 forward" in summary.action_share and "north" not in summary.report()
    # World frame with the thesis's swap: drone 1's code 0 flies west.
    swapped = summarize_behaviour("te", 1, head_on(0, "right"), frame="world", swap_drones=(1,))
    assert "0 west" in swapped.per_drone_action_share[1] and "0 east" in swapped.per_drone_action_share[0]


def test_single_drone_manoeuvres() -> None:
    (climb,) = one(CLIMB)
    assert climb.manoeuvre == "climb_over" and climb.trigger_step == 1 and climb.action == 5
    (direct,) = one(DIRECT)
    assert direct.manoeuvre == "direct" and direct.tags == ["direct"] and direct.planner_share == 1.0
    (oscillating,) = one(OSCILLATING)
    assert oscillating.manoeuvre == "oscillation" and oscillating.reversals == 6
    assert oscillating.outcome == "timeout"


def test_head_on_pass_sides_are_relative_to_travel() -> None:
    right = classify_episode(head_on(0, "right"))
    assert [d.manoeuvre for d in right.drones] == ["pass_right", "pass_right"]
    assert right.head_on and right.pattern == "pass_right+pass_right" and right.follows_priority is None
    assert [d.trigger_step for d in right.drones] == [2, 2] and {d.action for d in right.drones} == {0}
    left = classify_episode(head_on(1, "left"))
    assert [d.manoeuvre for d in left.drones] == ["pass_left", "pass_left"]


def test_yields_and_the_priority_rule() -> None:
    hover = classify_episode(hover_then_go())
    waiting, passing = hover.drones
    assert waiting.manoeuvre == "yield_hover" and passing.manoeuvre == "direct"
    assert waiting.yield_steps == 4 and waiting.yielded_to == 1 and waiting.action == 7
    # lower_coordinate_yields: drone 0 starts further south, so it is the one that should wait.
    assert waiting.priority == 0.0 and waiting.other_priority == 1.0 and hover.follows_priority is True
    # first_to_arrive: drone 1 with 8 m to go has the lower priority than drone 0 (6 m): drone 0
    # should not have waited.
    waiting_trace, _ = hover_then_go()
    far = trace(line(1, [5, 4, 3, 2, 1, 0, -1, -2, -3]), (1, -3), [3] * 8, drone=1)
    assert classify_episode([waiting_trace, far]).follows_priority is True
    wrong = classify_episode([waiting_trace, far], priority_rule="first_to_arrive")
    assert wrong.drones[0].manoeuvre == "yield_hover" and wrong.follows_priority is False
    (backing, _) = classify_episode(back_off()).drones
    assert backing.manoeuvre == "yield_back_off" and backing.action == 2 and backing.reversals == 1
    # Nobody passing: hovering is no yield.
    alone = one(trace(line(0, [0, 0, 0, 0, 1, 2]), (0, 2), [7, 7, 7, 3, 3]))[0]
    assert alone.manoeuvre == "hover" and alone.yield_steps == 0


def te_runs(right_seeds: int, left_seeds: int, episodes: int = 4) -> BehaviourAnalysis:
    runs = []
    for seed in range(right_seeds + left_seeds):
        side = "right" if seed < right_seeds else "left"
        traces = [t for e in range(episodes) for t in head_on(e, side)]
        runs.append(RunBehaviour(str(seed), classify(traces, run=str(seed))))
    return BehaviourAnalysis("two_drones_empty_relative", runs)


def test_competing_behaviours_are_reported_as_a_split() -> None:
    analysis = te_runs(3, 2)
    assert analysis.split() == {"pass_right": 0.6, "pass_left": 0.4}
    assert analysis.dominant() is None and analysis.seed_majorities() == {"pass_right": 3, "pass_left": 2}
    assert analysis.statements()[0] == ("two_drones_empty_relative: split: pass_right 60 %, pass_left 40 % "
                                        "of 40 successful drone-episodes")
    assert te_runs(5, 0).dominant() == "pass_right"
    data = analysis.to_dict()
    assert data["per_seed"][0]["success_counts"] == {"pass_right": 8} and data["seeds"] == 5


def observations(analysis: BehaviourAnalysis, traces_by_run: dict[str, list[Trace]], layout) -> dict:  # noqa: ANN001
    """What the scenario's `travel_others` feature reads before every step of every drone."""
    size = max(s.stop for s in layout.values())
    out = {}
    for label, traces in traces_by_run.items():
        for t in traces:
            others = [o for o in traces if o.episode == t.episode and o.drone != t.drone]
            path = np.asarray(t.positions_enu_m)
            rotation = travel_frame(path[0], np.asarray(t.goal_enu_m))
            rows = np.zeros((t.steps, size))
            for step in range(t.steps):
                other = np.asarray(others[0].positions_enu_m)[min(step, others[0].steps)]
                rows[step, layout["travel_others"].start:layout["travel_others"].start + 3] = \
                    rotation @ (other - path[step])
                rows[step, layout["own_priority"]] = float(t.drone == 1)  # drone 0 starts south: yields
            out[(label, t.episode, t.drone)] = rows
    return out


def aside_then_yield(episode: int) -> list[Trace]:
    """Drone 0 (lower priority) steps 1 m left, hovers 4 s while drone 1 comes down the line it
    left, then goes; drone 1 passes it 1 m to its right."""
    waiting = [(0, 0), (-1, 0), (-1, 0), (-1, 0), (-1, 0), (-1, 0)] + line(-1, [1, 2, 3, 4, 5, 6])
    passing = line(0, [7, 6, 5, 4, 3, 2, 1, 0, -1])
    return [trace(waiting, (0, 6), [1, 7, 7, 7, 7, 3, 3, 3, 3, 3, 3], drone=0, episode=episode),
            trace(passing, (0, -1), [3] * 8, drone=1, episode=episode)]


def test_a_yield_rule_covers_the_whole_approach_until_the_other_is_about_to_pass() -> None:
    """The networks' yielder hovered from 6 m (after stepping aside) and went on at 2 m: the rule
    hovers while the other is more than 2 m and at most 7 m (where it started) ahead. Starting at
    6 m, as the trigger alone says, a rule drone would first fly toward the other."""
    scenario_file = WORLDS / "two_drones_empty_relative.yaml"
    facts = scenario_facts(load_scenario(scenario_file), scenario_file)
    traces_by_run = {str(seed): [t for e in range(2) for t in aside_then_yield(e)] for seed in range(3)}
    runs = [RunBehaviour(label, classify(traces, run=label)) for label, traces in traces_by_run.items()]
    analysis = BehaviourAnalysis("two_drones_empty_relative", runs)
    assert {d.manoeuvre for e in analysis.episodes for d in e.drones if d.drone == 0} == {"yield_hover"}
    rules = {r.manoeuvre: r for r in candidate_rules(analysis, facts, observations(analysis, traces_by_run,
                                                                                        facts.layout))}
    hover = rules["yield_hover"]
    assert hover.in_yaml and hover.action == 7
    assert {"feature": "travel_others[1]", "op": ">", "value": 2.0} in hover.when
    assert {"feature": "travel_others[1]", "op": "<=", "value": 7.0} in hover.when
    assert hover.when[0] == {"feature": "own_priority", "op": "<", "value": 0.5}
    assert hover.text.startswith("another drone ahead, more than 2 and at most 7 m")


def test_candidate_rules_support_and_yaml_round_trip(tmp_path: Path) -> None:
    scenario_file = WORLDS / "two_drones_empty_relative.yaml"
    facts = scenario_facts(load_scenario(scenario_file), scenario_file)
    assert facts.frame == "goal" and facts.layout["travel_others"] == slice(6, 12)
    traces_by_run = {}
    runs = []
    for seed in range(5):  # 4 seeds pass right (one of their 4 episodes left), 1 seed passes left
        sides = ["right", "right", "right", "left"] if seed < 4 else ["left"] * 4
        traces = [t for e, side in enumerate(sides) for t in head_on(e, side)]
        traces_by_run[str(seed)] = traces
        runs.append(RunBehaviour(str(seed), classify(traces, run=str(seed))))
    analysis = BehaviourAnalysis("two_drones_empty_relative", runs)
    obs = observations(analysis, traces_by_run, facts.layout)
    rules = {r.manoeuvre: r for r in candidate_rules(analysis, facts, obs)}
    right, left = rules["pass_right"], rules["pass_left"]
    assert (right.support_seeds, right.seeds, right.support_episodes, right.episodes) == (4, 5, 12, 20)
    assert (left.support_seeds, left.support_episodes) == (1, 8)
    assert right.in_yaml and not left.in_yaml and "competes with pass_right" in left.note
    # At the sidestep the other drone is 4 m ahead, straight on: the condition says so.
    assert right.when == [{"feature": "travel_others[1]", "op": ">", "value": 0.0},
                          {"feature": "travel_others[1]", "op": "<=", "value": 4.0},
                          {"feature": "travel_others[0]", "op": ">=", "value": -0.5},
                          {"feature": "travel_others[0]", "op": "<=", "value": 0.5}]
    assert right.plain() == ("another drone ahead within 4 m (within 0.5 m sideways): move to its right "
                             "(action 0 right) (4 of 5 seeds, 12 of 20 successful episodes; competes with "
                             "pass_left (1 seeds))")
    assert right.agreement is not None and 0.0 < right.agreement <= 1.0

    document = rules_document(list(rules.values()), analysis, facts)
    path = write_rules_yaml(tmp_path / "te_rules.yaml", document)
    loaded = load_yaml(path).value
    assert loaded == document
    assert loaded["covers"] == ["two_drones_empty_relative.yaml"] and loaded["frame"] == "goal"
    assert [r["action"] for r in loaded["rules"]] == ["right", "toward goal"]
    assert loaded["rules"][0]["support"] == {"seeds": 4, "episodes": 12} and "when" not in loaded["rules"][-1]

    checks = {c.rule: c for c in thesis_checks(analysis, facts)}
    assert checks[3].applicable and checks[3].recovered
    assert (checks[3].support_seeds, checks[3].support_episodes, checks[3].episodes) == (4, 12, 20)
    assert not checks[2].applicable and not checks[5].applicable
    assert checks[0].recovered and checks[0].support_episodes == 40
    assert checks[3].line() == ("rule 3 (head-on: both move to their right): recovered: held in 4 of 5 seeds; "
                                "12 of 20 successful head-on episodes with both passing right (8 both left)")
    share, steps = fidelity(document, analysis, facts, obs)
    assert steps == 400 and share is not None and 0.0 < share < 1.0


def shifted(traces: list[Trace], dy: float) -> list[Trace]:
    """The same traces moved `dy` north (goals too)."""
    return [Trace(episode=t.episode, drone=t.drone, seed=t.seed, actions=t.actions, outcome=t.outcome,
                  positions_enu_m=[[x, y + dy, z] for x, y, z in t.positions_enu_m],
                  goal_enu_m=[t.goal_enu_m[0], t.goal_enu_m[1] + dy, t.goal_enu_m[2]]) for t in traces]


def climb_first(episode: int = 0) -> list[Trace]:
    """Drone 0 (south, lower priority) climbs 2 m straight up and then goes north first while
    drone 1 (north, right of way) waits 4 s: through a window at y = 3 against the priority rule."""
    eager = trace(line(0, [0, 0, 0, 2, 4, 6]), (0, 6), [4, 4, 3, 3, 3], drone=0, episode=episode,
                  z=[2.5, 3.5, 4.5, 4.5, 4.5, 4.5])
    waiting = trace(line(1, [6, 6, 6, 6, 6, 4, 2, 0]), (1, 0), [7, 7, 7, 7, 3, 3, 3], drone=1, episode=episode)
    return [eager, waiting]


def test_yield_rule_and_thesis_rule_5_on_a_window_scenario() -> None:
    scenario_file = WORLDS / "two_drones_window.yaml"
    scenario = load_scenario(scenario_file)
    facts = scenario_facts(scenario, scenario_file)
    assert facts.opening and facts.num_drones == 2
    (window,) = openings(scenario.world.obstacles)  # the middle wall's, at y = 0, 4.5-5.7 m up
    assert window.center_enu_m == pytest.approx((0.0, 0.0, 5.1)) and window.normal_enu == pytest.approx((0, 1, 0))

    def classified(traces: list[Trace], label: str) -> RunBehaviour:
        return RunBehaviour(label, classify(shifted(traces, -3.0), run=label, shared_openings=(window,)))

    runs = [classified([t for e in range(3) for t in hover_then_go(e)], str(seed)) for seed in range(3)]
    runs.append(classified(back_off(), "3"))
    runs.append(classified([t for e in range(3) for t in climb_first(e)], "4"))
    analysis = BehaviourAnalysis("two_drones_window", runs)
    # Seed 4's waiting (drone 1, right of way) is one hover step with drone 0 near and under way:
    # no yield by the hover/back-off measure. The order through the window shows it.
    assert analysis.yield_priority() == (10, 10)
    # Drone 1 (passing) is through after 3 steps, drone 0 after 8 (hovering) or 9 (backing off).
    first = analysis.runs[0].episodes[0]
    assert [d.opening_step for d in first.drones] == [8, 3] and first.order_follows_priority is True
    late = analysis.runs[4].episodes[0]
    assert [d.opening_step for d in late.drones] == [4, 6] and late.order_follows_priority is False
    assert analysis.passing_order() == (10, 13)
    assert "through the opening in priority order in 10 of 13 episodes" in analysis.statements()
    checks = {c.rule: c for c in thesis_checks(analysis, facts)}
    assert checks[5].recovered and (checks[5].support_seeds, checks[5].seeds) == (4, 5)
    assert (checks[5].support_episodes, checks[5].episodes) == (10, 13)
    assert "9 of them hovering, 1 backing off" in checks[5].evidence
    assert checks[4].recovered and not checks[3].applicable
    rules = {r.manoeuvre: r for r in candidate_rules(analysis, facts)}
    # TW's features have no travel_others, and no observations were given: text only.
    assert not rules["yield_hover"].flyable and not rules["yield_hover"].in_yaml
    assert rules["yield_hover"].support_seeds == 3 and rules["yield_back_off"].support_seeds == 1
    assert rules["direct"].in_yaml and rules["direct"].action_name == "toward goal"


def test_climb_over_rule_from_lidar_and_thesis_rule_2() -> None:
    scenario_file = WORLDS / "obstacle.yaml"
    facts = scenario_facts(load_scenario(scenario_file), scenario_file)
    assert facts.lone_obstacle and "lidar" in facts.layout
    lidar = facts.layout["lidar"]
    runs, obs = [], {}
    for seed in range(3):
        traces = [CLIMB] if seed < 2 else [DIRECT]
        runs.append(RunBehaviour(str(seed), classify(traces, run=str(seed))))
        rows = np.full((traces[0].steps, lidar.stop), facts.lidar_range_m)
        rows[1, lidar.start + 17] = 1.13  # the forward ray sees the block when the climb starts
        obs[(str(seed), 0, 0)] = rows
    analysis = BehaviourAnalysis("obstacle", runs)
    rules = {r.manoeuvre: r for r in candidate_rules(analysis, facts, obs)}
    climb = rules["climb_over"]
    assert climb.when == [{"feature": "lidar[17]", "op": "<=", "value": 1.2}] and climb.action_name == "up"
    assert (climb.support_seeds, climb.support_episodes, climb.in_yaml) == (2, 2, True)
    checks = {c.rule: c for c in thesis_checks(analysis, facts)}
    assert checks[2].recovered and (checks[2].support_seeds, checks[2].seeds) == (2, 3)


def test_recording_env_keeps_what_the_policy_saw() -> None:
    from sitl_bridge.rl.analysis.behaviour_runs import RecordingEnv
    from sitl_bridge.rl.common.drones_env import scenario_env_factory
    from sitl_bridge.rl.evaluation.evaluate import evaluate_on

    seen: list[np.ndarray] = []

    def policy(obs: np.ndarray) -> int:
        seen.append(obs.copy())
        return 3 if len(seen) % 4 else 7

    env = RecordingEnv(scenario_env_factory(WORLDS / "empty.yaml")(0))
    try:
        _, traces = evaluate_on(env, policy, world="empty", episodes=2, seed=0)
    finally:
        env.close()
    recorded = env.observations
    assert sorted(recorded) == [(0, 0), (1, 0)]
    assert [len(recorded[(t.episode, 0)]) for t in traces] == [t.steps for t in traces]
    assert np.array_equal(np.concatenate([recorded[(0, 0)], recorded[(1, 0)]]), np.array(seen))


def test_rules_command_over_two_runs_writes_a_yaml(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import argparse
    import json

    from sitl_bridge.commands import rules, train

    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers()
    train.register(sub)
    rules.register(sub)

    def cli(*argv: str) -> int:
        args = parser.parse_args(list(argv))
        return args.func(args)

    for seed in ("0", "1"):
        assert cli("train", str(WORLDS / "empty.yaml"), "--episodes", "1", "--seed", seed, "--out",
                   str(tmp_path / "runs"), "--batch-size", "16", "--layers", "2", "--hidden-units", "16",
                   "--eval-every", "0", "--eval-episodes", "1", "--no-progress") == 0
    capsys.readouterr()
    runs = sorted(str(p) for p in (tmp_path / "runs").iterdir())
    out = tmp_path / "rules.yaml"
    assert cli("rules", *runs, "--episodes", "2", "--out", str(out), "--json") == 0
    report = json.loads(capsys.readouterr().out)
    assert [s["label"] for s in report["behaviour"]["per_seed"]] == ["0", "1"]
    assert sum(sum(s["counts"].values()) for s in report["behaviour"]["per_seed"]) == 4
    assert report["episodes"] == 4 and report["frame"] == "world"
    assert [c["rule"] for c in report["thesis_rules"]] == [0, 1, 2, 3, 4, 5]
    document = load_yaml(out).value
    assert document == report["rules_yaml"] and document["covers"] == ["empty.yaml"]
    assert document["rules"][-1]["action"] == "toward goal"


def test_no_success_gives_no_rules_and_no_evidence() -> None:
    crashed = [t for e in range(2) for t in head_on(e, "right")]
    for t in crashed:
        t.outcome = "crash"
    analysis = BehaviourAnalysis("two_drones_empty_relative", [RunBehaviour("0", classify(crashed, run="0"))])
    facts = scenario_facts(load_scenario(WORLDS / "two_drones_empty_relative.yaml"), "two_drones_empty_relative.yaml")
    assert analysis.split() == {} and analysis.dominant() is None
    assert candidate_rules(analysis, facts) == []
    rule3 = thesis_checks(analysis, facts)[3]
    assert rule3.recovered is None and rule3.line().endswith("no evidence in 1 seeds: no successful head-on episodes")
    document = rules_document([], analysis, facts)
    assert [r["action"] for r in document["rules"]] == ["toward goal"]



def test_a_drone_that_drops_below_the_other_dives_under() -> None:
    """TE's most common learned pass: one drone descends about a metre, the other flies straight on."""
    low = trace(line(0, list(range(11))), (0, 10), [4, 4] + [6] * 8,
                z=[2.5, 2.0, 1.5, 1.4, 1.4, 1.4, 1.5, 1.7, 1.9, 2.2, 2.5])
    high = trace(line(0, [10 - y for y in range(11)]), (0, 0), [6] * 10, drone=1)
    episode = classify_episode([low, high])
    assert [d.manoeuvre for d in episode.drones] == ["dive_under", "direct"]


def test_who_dives_follows_a_priority_convention_that_can_differ_by_seed() -> None:
    """Mirror-image drones need the priority input to break the symmetry: in seeds 0-2 the drone
    with right of way (drone 1) descends below the other, in seed 3 the one without. The rule
    keeps the convention most seeds follow, as a condition on `own_priority`, and says the rest."""
    scenario_file = WORLDS / "two_drones_empty_relative.yaml"
    facts = scenario_facts(load_scenario(scenario_file), scenario_file)
    dip = [2.5, 2.0, 1.5, 1.4, 1.4, 1.4, 1.5, 1.7, 1.9, 2.2, 2.5]
    traces_by_run, runs = {}, []
    for seed in range(4):
        diver = 1 if seed < 3 else 0
        traces = []
        for e in range(2):
            north = trace(line(0, list(range(11))), (0, 10), ([4, 4] if diver == 0 else [6, 6]) + [6] * 8,
                          episode=e, z=dip if diver == 0 else None)
            south = trace(line(0, [10 - y for y in range(11)]), (0, 0), ([4, 4] if diver == 1 else [6, 6]) + [6] * 8,
                          drone=1, episode=e, z=dip if diver == 1 else None)
            traces += [north, south]
        traces_by_run[str(seed)] = traces
        runs.append(RunBehaviour(str(seed), classify(traces, run=str(seed))))
    analysis = BehaviourAnalysis("two_drones_empty_relative", runs)
    rules = {r.manoeuvre: r for r in candidate_rules(analysis, facts, observations(analysis, traces_by_run,
                                                                                   facts.layout))}
    dive = rules["dive_under"]
    assert dive.when[0] == {"feature": "own_priority", "op": ">=", "value": 0.5}
    # It ends at the height difference the networks built while the other was ahead (1.1 m: 2.5
    # against 1.4), so a rule flying it stops descending there instead of into the ground.
    assert dive.when[-1] == {"feature": "travel_others[2]", "op": "<", "value": 1.1}
    assert "not yet 1.1 m below it: descend below it" in dive.text
    assert (dive.support_seeds, dive.support_episodes) == (3, 6)
    assert "1 other seed(s) the drone without right of way" in dive.note
    assert dive.action_name == "down" and dive.in_yaml


def test_a_climb_to_the_window_becomes_a_rule_that_flies_the_window(tmp_path: Path) -> None:
    """The thesis's W behaviour (5 5 5 5, then on through the window): the climb to the opening
    is its own manoeuvre, and its rule tests the ray that tells the climbing steps from the others
    (the forward ray sees the wall until the drone is level with the window), not the side wall
    that reads shorter at every step; of the rays that score alike, the middle one (straight ahead).
    Flown, the rules pass the window."""
    scenario_file = WORLDS / "window.yaml"
    scenario = load_scenario(scenario_file)
    facts = scenario_facts(scenario, scenario_file)
    wall_openings = openings(scenario.world.obstacles)  # the north wall's: y = 4, 4.5-5.7 m up
    path = [[0, 0, 1], [0, 0, 2], [0, 0, 3], [0, 0, 4], [0, 0, 5], [0, 1, 5], [0, 2, 5], [0, 3, 5], [0, 4, 5],
            [0, 5, 5], [0, 6, 5]]
    lidar = facts.layout["lidar"]
    climb = Trace(episode=0, drone=0, seed=100, actions=[5] * 4 + [6] * 6, outcome="goal",
                  positions_enu_m=path, goal_enu_m=[0, 6, 5])
    runs, obs = [], {}
    for seed in range(2):
        runs.append(RunBehaviour(str(seed), classify([climb], run=str(seed), shared_openings=wall_openings)))
        rows = np.full((10, lidar.stop), facts.lidar_range_m)
        rows[:, lidar.start] = 3.5  # a side wall, as near at every step
        # the north wall ahead while below the window, seen alike by the rays 10 deg either side
        rows[:4, lidar.start + 16:lidar.start + 19] = 3.9
        obs[(str(seed), 0, 0)] = rows
    (drone,) = runs[0].episodes[0].drones
    assert drone.manoeuvre == "to_opening" and (drone.trigger_step, drone.action) == (0, 5)
    (plain,) = one(climb)
    assert plain.manoeuvre == "direct"  # without the world's openings nothing names the climb
    slanting = [[0, 0.8 * k, 1 + 0.6 * k] for k in range(8)]  # toward a goal higher up: direct flight
    (direct,) = one(Trace(episode=0, drone=0, seed=100, actions=[6] * 7, outcome="goal",
                          positions_enu_m=slanting, goal_enu_m=[0, 6, 5.2]), shared_openings=wall_openings)
    assert direct.manoeuvre == "direct"
    analysis = BehaviourAnalysis("window", runs)
    rules = {r.manoeuvre: r for r in candidate_rules(analysis, facts, obs)}
    rise = rules["to_opening"]
    assert rise.when == [{"feature": "lidar[17]", "op": "<=", "value": 3.9}] and rise.action_name == "up"
    assert rise.text.startswith("something within 3.9 m ahead (lidar[17]): change height toward the opening")
    assert rise.in_yaml and (rise.support_seeds, rise.support_episodes) == (2, 2)
    written = write_rules_yaml(tmp_path / "window.yaml", rules_document(list(rules.values()), analysis, facts))
    result, _, _ = evaluate_rules(written, scenario_file, episodes=2)
    assert result.success_rate == 1.0


def test_of_two_alike_rays_in_the_middle_the_rule_tests_the_better_one() -> None:
    """Rays 45 (below, 22 deg ahead) and 46 (below, 37 deg ahead) tell the climbing steps apart
    nearly as well (J 0.42 and 0.58, within one standard error of 0.19): both are the fan's middle, and
    the rule tests the one that scores better, not the lower index."""
    scenario_file = WORLDS / "obstacle.yaml"
    facts = scenario_facts(load_scenario(scenario_file), scenario_file)
    lidar = facts.layout["lidar"]
    after = []
    for run in range(2):  # per run: 4 climbing steps, then 6 others
        rows = np.full((10, lidar.stop), facts.lidar_range_m)
        rows[:4, lidar.start + 45:lidar.start + 47] = 3.0
        rows[3 * run, lidar.start + 46] = facts.lidar_range_m  # one climbing step each sees nothing
        rows[3 * run, lidar.start + 45] = facts.lidar_range_m
        rows[5, lidar.start + 45:lidar.start + 47] = 3.0  # a later step sees it too
        rows[7 + run, lidar.start + 45] = 3.0  # ray 45 also on one more: a little worse
        after.append((str(run), rows, [5] * 4 + [6] * 6))
    when, text = _lidar_condition(after, 5, facts)
    assert when == [{"feature": "lidar[46]", "op": "<=", "value": 3.0}]
    assert text == "something within 3 m below, 37 deg ahead (lidar[46])"
