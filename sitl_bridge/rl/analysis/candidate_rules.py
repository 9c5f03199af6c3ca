"""Candidate traffic rules from classified behaviour across seeds, in words and as a rules YAML.

Each manoeuvre that successful episodes show becomes a candidate rule: the situation in which it
started (read from the observation before its first step, so the condition is over the
scenario's own observation features), the action the policy flew there (named in the scenario's
action frame) and its support: the seeds in which it shows in at least half of the successful
episodes, and the successful episodes that show it. Competing manoeuvres (left vs right, hover vs
back off) stay side by side in the candidate list; the YAML, whose first matching rule wins,
takes the better supported one and says so. The YAML's format is the one `eval --rules` flies
(name, covers, frame, source, rules of text/when/action/support).

`thesis_checks` maps the thesis's rules 0-5 to checks on the same classifications: recovered
(held in more than half of the seeds), not recovered, or not applicable to the scenario.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import yaml

from sitl_bridge.rl.analysis.behaviour import BehaviourAnalysis, EpisodeBehaviour, split_text
from sitl_bridge.rl.common.action_names import action_code, action_name

ANALYSIS_VERSION = 7
"""Bumped when the classification, the rule extraction or the rules' verification changes what
they report, so the report's cached behaviour and rules are made again (2: passing order, rule 5
by it, the end of a climb or dive under another drone; 3: traffic rule sets flown in the
one-drone scenarios before them, their rules on the other drone left out; 4: climbs to a wall's
opening, `to_opening`, a rule of their own; a lidar condition on the ray that tells the
manoeuvre's steps apart; 5: of the rays alike within one standard error, the middle one; 6: of
two middles, the better; 7: a yield over the other's whole approach, until it is about to pass)."""
SEED_SUPPORT_SHARE = 0.5
"""A manoeuvre holds in a seed when it shows in at least this share of its successful episodes."""
YAML_MIN_SEED_SHARE = 0.5
"""A candidate enters the YAML when it holds in at least this share of the seeds (a majority
behaviour, not one run's habit)."""
THRESHOLD_STEP = 0.1
"""Condition thresholds are rounded outward to this (metres): readable, and still true at the
observed triggers."""
LATERAL_MARGIN_M = 0.5
"""Sideways slack added to the largest sideways offset of the other drone seen at a trigger."""
GROUND_CRASH_M = 0.5
"""A crash ending this low above the ground hit the ground (thesis rule 0)."""
ORDER_SEED_SHARE = 0.8
"""Thesis rule 5 holds in a seed when this share of its successful episodes went through the
opening in priority order (half would be chance: one of the two goes first anyway)."""
PLANNER_SHARE = 0.5
"""Direct flights with at least this share of action 6 use the planner's path (thesis rule 1)."""

RULE_MANOEUVRES = ("yield_hover", "yield_back_off", "pass_right", "pass_left", "climb_over", "dive_under",
                   "to_opening", "direct")
"""Manoeuvres that make rules, in YAML order (most specific situation first, `direct` last)."""
COMPETING = (("pass_right", "pass_left"), ("yield_hover", "yield_back_off"), ("climb_over", "dive_under"))
WORDS = {"direct": "fly toward the goal", "climb_over": "climb over it", "dive_under": "descend below it",
         "pass_left": "move to its left",
         "pass_right": "move to its right", "yield_hover": "hover until it has passed",
         "yield_back_off": "move back until it has passed", "to_opening": "change height toward the opening"}
TOWARD_GOAL = 6
"""The planner's action (the thesis's code 6), the rule for the straight path."""
OTHER_DRONE = ("yield_hover", "yield_back_off")
"""Manoeuvres that are about another drone in every scenario; passes are when there are others."""
ABOUT_WORLD = ("to_opening",)
"""Manoeuvres that are about the world's geometry (lidar) even when there are other drones."""

Observations = Mapping[tuple[str, int, int], np.ndarray]
"""(run label, episode, drone) -> that drone's observation before each of its steps (steps x size)."""


@dataclass(frozen=True)
class ScenarioFacts:
    """What rule building needs to know about a scenario."""

    file: str
    """Scenario file name (the YAML's `covers`)."""
    frame: str = "world"
    layout: Mapping[str, slice] = field(default_factory=dict)
    """Observation feature name -> its slice of the observation vector."""
    num_drones: int = 1
    lone_obstacle: bool = False
    """Exactly one static obstacle that is not a wall (thesis rule 2's situation)."""
    opening: bool = False
    """A wall with an opening (thesis rules 4 and 5)."""
    lidar_range_m: float = 5.0
    lidar_labels: tuple[str, ...] = ()
    """Each lidar ray's direction in words (`sensors.lidar.ray_labels`), in observation order."""
    lidar_groups: tuple[str, ...] = ()
    """Each lidar ray's group (horizontal, up, down), in observation order."""


def scenario_facts(scenario, file: str | Path) -> ScenarioFacts:  # noqa: ANN001 - envs.scenario.Scenario
    """Facts of a loaded `envs.scenario.Scenario` (its file name as `file`)."""
    layout, start = {}, 0
    for feature in scenario.task.observation:
        layout[feature.name] = slice(start, start + feature.size)
        start += feature.size
    static = [o for o in scenario.world.obstacles if not o.dynamic]
    lidar = next((f for f in scenario.task.observation if f.name == "lidar"), None)
    return ScenarioFacts(
        file=Path(file).name, frame=scenario.task.action.frame, layout=layout, num_drones=scenario.num_drones,
        lone_obstacle=len(static) == 1 and static[0].shape.kind != "wall",
        opening=any(o.shape.opening is not None for o in static),
        lidar_range_m=scenario.limits.lidar_range_m,
        lidar_labels=lidar.labels if lidar else (), lidar_groups=lidar.groups if lidar else ())


@dataclass
class CandidateRule:
    """One candidate rule: situation -> action, with its support across seeds."""

    manoeuvre: str
    text: str
    action: int
    action_name: str
    when: list[dict] = field(default_factory=list)
    """Conditions over observation features (`{feature, op, value}`), all must hold."""
    support_seeds: int = 0
    seeds: int = 0
    support_episodes: int = 0
    episodes: int = 0
    """Successful episodes of all seeds (the denominator of `support_episodes`)."""
    flyable: bool = True
    """Its conditions are expressible in the scenario's features (else text only)."""
    in_yaml: bool = False
    note: str = ""
    agreement: float | None = None
    """Share of recorded steps where this rule is the first that holds at which the policy flew
    its action (how well the rule imitates the network there)."""

    def plain(self) -> str:
        """`another drone ahead within 3 m: move to its right (9 of 10 seeds, 412 episodes)`."""
        note = f"; {self.note}" if self.note else ""
        return (f"{self.text} ({self.support_seeds} of {self.seeds} seeds, "
                f"{self.support_episodes} of {self.episodes} successful episodes{note})")

    def to_dict(self) -> dict:
        return {**asdict(self), "plain": self.plain()}


def _successes(analysis: BehaviourAnalysis) -> dict[str, list[EpisodeBehaviour]]:
    return {run.label: [e for e in run.episodes if e.success] for run in analysis.runs}


def support(analysis: BehaviourAnalysis, manoeuvre: str) -> tuple[int, int]:
    """(seeds in which `manoeuvre` holds, successful episodes showing it)."""
    seeds = episodes = 0
    for wins in _successes(analysis).values():
        showing = sum(e.shows(manoeuvre) for e in wins)
        episodes += showing
        seeds += bool(wins) and showing >= SEED_SUPPORT_SHARE * len(wins)
    return seeds, episodes


def _up(value: float) -> float:
    return round(math.ceil(value / THRESHOLD_STEP - 1e-9) * THRESHOLD_STEP, 6)


def _down(value: float) -> float:
    return round(math.floor(value / THRESHOLD_STEP + 1e-9) * THRESHOLD_STEP, 6)


def _feature(layout: Mapping[str, slice], name: str, index: int) -> str:
    block = layout[name]
    return name if block.stop - block.start == 1 else f"{name}[{index}]"


After = list[tuple[str, np.ndarray, list[int]]]
"""(run, observations, actions) from the first step of a manoeuvre on, per drone-episode."""


def _from_trigger(analysis: BehaviourAnalysis, manoeuvre: str, observations: Observations,
                  *, from_start: bool = False) -> After:
    """(run, observations and actions from the first step of `manoeuvre` on) of every successful
    drone-episode that shows it and has its observations recorded; with `from_start`, from the
    episode's first step instead."""
    found = []
    for episode in analysis.episodes:
        if not episode.success:
            continue
        for d in episode.drones:
            obs = observations.get((episode.run, episode.episode, d.drone))
            if d.manoeuvre == manoeuvre and d.trigger_step is not None and obs is not None \
                    and d.trigger_step < len(obs):
                first = 0 if from_start else d.trigger_step
                found.append((episode.run, np.asarray(obs[first:], dtype=float), d.actions[first:]))
    return found


def _triggers(after: After) -> tuple[np.ndarray, list[str]]:
    """Observations before the first step of the manoeuvre (rows), and the run (seed) each row
    comes from."""
    return np.array([rows[0] for _, rows, _ in after]), [run for run, _, _ in after]


def _priority_convention(rows: np.ndarray, runs: list[str], facts: ScenarioFacts,
                         ) -> tuple[np.ndarray, list[str], bool | None, str]:
    """Which drone of a pair does the manoeuvre, by its right of way (`own_priority`): a shared
    policy needs the priority input to break the symmetry of mirror-image situations, and each
    seed may learn the other convention. Returns the rows of the convention most seeds follow,
    their runs, whether the drone doing it has right of way (None: no priority input, or the
    drones of both priorities do it in every seed) and a note on the seeds that differ."""
    if "own_priority" not in facts.layout or not len(rows):
        return rows, runs, None, ""
    high = rows[:, facts.layout["own_priority"].start] >= 0.5
    by_run: dict[str, set[bool]] = {}
    for run, h in zip(runs, high.tolist(), strict=True):
        by_run.setdefault(run, set()).add(h)
    pure = {run: next(iter(kinds)) for run, kinds in by_run.items() if len(kinds) == 1}
    if not pure:
        return rows, runs, None, ""
    with_way = sum(pure.values())
    convention = with_way >= len(pure) - with_way  # ties: the drone with right of way
    keep = [k for k, run in enumerate(runs) if pure.get(run) == convention]
    others = [run for run, h in pure.items() if h != convention]
    note = (f"in {len(others)} other seed(s) the drone {'without' if convention else 'with'} right of way "
            "does it instead (the priority input breaks the symmetry; the convention differs by seed)"
            if others else "")
    return rows[keep], [runs[k] for k in keep], convention, note


def _yield_span(after: After, starts: After, base: int) -> tuple[float, float] | None:
    """For a yield, "until it has passed", as far as the other drone ahead (travel frame) says:
    (the distance below which the networks stopped yielding, the median over the drone-episodes
    of the other's distance ahead at the first step after the trigger that flew another action
    than the trigger's, rounded down; the largest distance ahead at the episodes' starts,
    rounded up). A rule without memory cannot tell "before my yield began" from "during it", so
    it yields over the other's whole approach: starting it only where the networks' yields began
    (after stepping aside or waiting low) lets the rule's drone fly into the conflict first.
    None when no yield ended with the other still ahead or the other was not ahead at a start."""
    ends = []
    for _, rows, actions in after:
        end = next((k for k in range(1, len(actions)) if actions[k] != actions[0]), None)
        if end is not None and end < len(rows):
            ends.append(float(rows[end, base + 1]))
    first = np.array([rows[0, base + 1] for _, rows, _ in starts])
    if not ends or not len(first) or float(first.min()) <= 0.0:
        return None
    return _down(max(0.0, float(np.median(ends)))), _up(float(first.max()))


def _drone_condition(rows: np.ndarray, facts: ScenarioFacts, manoeuvre: str,
                     span: tuple[float, float] | None = None) -> tuple[list[dict], str] | None:
    """Another drone ahead (travel frame) within the largest distance seen at the triggers, or,
    for a yield with its `span` (`_yield_span`), ahead by more than where the networks stopped
    yielding and at most as far as at the episodes' starts."""
    if "travel_others" not in facts.layout:
        return None
    base = facts.layout["travel_others"].start
    ahead, side = rows[:, base + 1], rows[:, base]
    if float(ahead.min()) <= 0.0:
        return None  # the other was not always ahead when it started: not this situation
    near, reach = span if span is not None else (0.0, 0.0)
    reach = max(reach, _up(float(ahead.max())))  # every trigger inside it, whatever the starts said
    width = _up(float(np.abs(side).max()) + LATERAL_MARGIN_M)
    forward, sideways = _feature(facts.layout, "travel_others", 1), _feature(facts.layout, "travel_others", 0)
    when = [{"feature": forward, "op": ">", "value": near}, {"feature": forward, "op": "<=", "value": reach},
            {"feature": sideways, "op": ">=", "value": -width}, {"feature": sideways, "op": "<=", "value": width}]
    situation = (f"another drone ahead, more than {near:g} and at most {reach:g} m (within {width:g} m sideways)"
                 if near > 0.0 else f"another drone ahead within {reach:g} m (within {width:g} m sideways)")
    if manoeuvre in OTHER_DRONE and "own_priority" in facts.layout:
        priority = rows[:, facts.layout["own_priority"].start]
        if float(priority.max()) < 0.5:
            when.insert(0, {"feature": _feature(facts.layout, "own_priority", 0), "op": "<", "value": 0.5})
            situation += " and own priority lower"
    return when, situation


def _vertical_stop(after: After, manoeuvre: str, facts: ScenarioFacts, runs: set[str]) -> dict | None:
    """For a climb over or a dive under another drone: the condition that ends it, the other
    drone not yet as far below / above as the networks took it (the median, over the episodes of
    the kept runs, of the largest height difference built while the other was still ahead).
    Without it a rule keeps descending as long as the other is ahead (TE: into the ground)."""
    if manoeuvre not in ("climb_over", "dive_under") or "travel_others" not in facts.layout:
        return None
    ahead, up = facts.layout["travel_others"].start + 1, facts.layout["travel_others"].start + 2
    sign = 1.0 if manoeuvre == "dive_under" else -1.0  # the other above me (dive) or below (climb)
    gaps = []
    for run, rows, _ in after:
        rows = rows[rows[:, ahead] > 0.0]
        if run in runs and len(rows):
            gaps.append(float((sign * rows[:, up]).max()))
    gap = _down(float(np.median(gaps))) if gaps else 0.0
    if gap <= 0.0:
        return None
    feature = _feature(facts.layout, "travel_others", 2)
    return {"feature": feature, "op": "<" if sign > 0 else ">", "value": round(sign * gap, 6)}


def _lidar_condition(after: After, code: int, facts: ScenarioFacts) -> tuple[list[dict], str] | None:
    """`ray <= reach` for the ray that best tells the steps from the trigger on where the network
    flew the manoeuvre's action `code` from those where it flew another (Youden's J: share of the
    former where it holds minus share of the latter); reach is the longest reading of that ray at
    the triggers where it saw something. The ray that merely read shortest would often be the
    ground below or a side wall, true whatever the network does. None when no ray tells them
    apart (J <= 0). Of the neighbours that score within one standard error of the best ray, the
    middle one (of two in the middle, the better)."""
    if "lidar" not in facts.layout or not after:
        return None
    block = facts.layout["lidar"]
    triggers = np.array([rows[0, block] for _, rows, _ in after])
    seen = triggers < facts.lidar_range_m - 1e-6
    reach = {int(r): _up(float(triggers[seen[:, r], r].max())) for r in np.flatnonzero(seen.any(axis=0))}
    steps = np.concatenate([rows[:len(actions), block] for _, rows, actions in after])
    flew = np.concatenate([np.asarray(actions[:len(rows)]) == code for _, rows, actions in after])
    if not flew.any():
        return None

    def rates(r: int) -> tuple[float, float]:
        """Share of the steps that flew `code` where ray r's condition holds, and of the others."""
        holds = steps[:, r] <= reach[r]
        return float(holds[flew].mean()), float(holds[~flew].mean()) if (~flew).any() else 0.0

    shares = {r: rates(r) for r in reach}
    scores = {r: hit - false for r, (hit, false) in shares.items()}
    ray = max(scores, key=scores.__getitem__, default=None)
    if ray is None or scores[ray] <= 0.0:
        return None
    # Neighbouring rays that see the same obstacle score alike; those within one standard error
    # of the best (the 1-SE rule) are not told apart by the data, and the middle of that fan is
    # the least sensitive to where it points (a side ray sees past an opening's edge).
    hit, false = shares[ray]
    standard_error = np.sqrt(hit * (1 - hit) / flew.sum() + false * (1 - false) / max((~flew).sum(), 1))

    def alike(r: int) -> bool:  # a fan stays within one group of rays (horizontal, up, down)
        return (r in scores and facts.lidar_groups[r:r + 1] == facts.lidar_groups[ray:ray + 1]
                and scores[r] >= scores[ray] - standard_error)

    low = high = ray
    while alike(low - 1):
        low -= 1
    while alike(high + 1):
        high += 1
    ray = max({(low + high) // 2, (low + high + 1) // 2}, key=scores.__getitem__)  # of two middles, the better
    reach = reach[ray]
    feature = _feature(facts.layout, "lidar", ray)
    where = f"{facts.lidar_labels[ray]} ({feature})" if ray < len(facts.lidar_labels) else f"on {feature}"
    return [{"feature": feature, "op": "<=", "value": reach}], f"something within {reach:g} m {where}"


def _candidate(analysis: BehaviourAnalysis, manoeuvre: str, facts: ScenarioFacts,
               observations: Observations) -> CandidateRule | None:
    seeds, episodes = support(analysis, manoeuvre)
    if not episodes:
        return None
    actions = [d.action for e in analysis.episodes if e.success for d in e.drones
               if d.manoeuvre == manoeuvre and d.action is not None]
    if not actions:  # supported only by episodes whose manoeuvre has no single action (e.g. mixed codes)
        return None
    code = max(set(actions), key=lambda a: (actions.count(a), -a))
    rule = CandidateRule(manoeuvre=manoeuvre, text="", action=code, action_name=action_name(code, facts.frame),
                         support_seeds=seeds, seeds=len(analysis.runs), support_episodes=episodes,
                         episodes=sum(len(w) for w in _successes(analysis).values()))
    if manoeuvre == "direct":
        # The straight start-goal path is what action 6 flies for every drone; the network's own
        # codes for it differ per drone in the world frame, so they are only reported.
        rule.action, rule.action_name = TOWARD_GOAL, action_name(TOWARD_GOAL, facts.frame)
        rule.text = f"otherwise {WORDS[manoeuvre]} (action {TOWARD_GOAL} {rule.action_name})"
        rule.note = f"the network flew it mostly with action {code} {action_name(code, facts.frame)}"
        return rule
    doing = f"{WORDS[manoeuvre]} (action {code} {rule.action_name})"
    about_drone = manoeuvre in OTHER_DRONE or (facts.num_drones > 1 and manoeuvre not in ABOUT_WORLD)
    after = _from_trigger(analysis, manoeuvre, observations)
    rows, runs = _triggers(after)
    convention, convention_note = None, ""
    if about_drone and manoeuvre not in OTHER_DRONE and facts.num_drones > 1:
        rows, runs, convention, convention_note = _priority_convention(rows, runs, facts)
        if convention is not None:  # support: only the seeds that follow the convention kept
            followers = set(runs)
            rule.support_seeds = min(rule.support_seeds, len(followers))
            rule.support_episodes = sum(e.shows(manoeuvre) for e in analysis.episodes
                                        if e.success and e.run in followers)
            rule.note = convention_note
    condition = None
    if len(rows):
        span = None
        if manoeuvre in OTHER_DRONE and "travel_others" in facts.layout:
            span = _yield_span(after, _from_trigger(analysis, manoeuvre, observations, from_start=True),
                               facts.layout["travel_others"].start)
        condition = (_drone_condition(rows, facts, manoeuvre, span) if about_drone
                     else _lidar_condition(after, code, facts))
        if condition is not None and convention is not None:
            when, situation = condition
            when.insert(0, {"feature": _feature(facts.layout, "own_priority", 0),
                            "op": ">=" if convention else "<", "value": 0.5})
            condition = when, situation + (" and own right of way" if convention else " and no right of way")
        stop = _vertical_stop(after, manoeuvre, facts, set(runs)) if about_drone else None
        if condition is not None and stop is not None:
            when, situation = condition
            where = "below" if manoeuvre == "dive_under" else "above"
            condition = when + [stop], f"{situation}, not yet {abs(stop['value']):g} m {where} it"
    if condition is None:
        rule.flyable = False
        rule.text = f"{'another drone near' if about_drone else 'an obstacle ahead'}: {doing}"
        needs = "travel_others" if about_drone else "lidar"
        if not len(rows):
            rule.note = "no observations recorded"
        elif needs not in facts.layout:
            rule.note = f"not expressible in this scenario's features (needs {needs})"
        else:
            rule.note = ("the other drone was not always ahead when it started" if about_drone
                         else "no lidar ray tells where the network did it from where it did not")
        return rule
    rule.when, situation = condition
    rule.text = f"{situation}: {doing}"
    return rule


def candidate_rules(analysis: BehaviourAnalysis, facts: ScenarioFacts,
                    observations: Observations | None = None) -> list[CandidateRule]:
    """Candidate rules in YAML order; `in_yaml` marks those the rules YAML keeps."""
    observations = observations or {}
    found = {m: r for m in RULE_MANOEUVRES if (r := _candidate(analysis, m, facts, observations)) is not None}
    dropped = set()
    for a, b in COMPETING:
        if a in found and b in found:
            keep, drop = sorted((found[a], found[b]),
                                key=lambda r: (-r.support_seeds, -r.support_episodes, r.manoeuvre))
            drop.note = "; ".join(filter(None, [drop.note, f"competes with {keep.manoeuvre} (kept in the YAML)"]))
            keep.note = "; ".join(filter(None, [keep.note, f"competes with {drop.manoeuvre} "
                                                           f"({drop.support_seeds} seeds)"]))
            dropped.add(drop.manoeuvre)
    rules = list(found.values())
    for rule in rules:
        majority = rule.support_seeds >= YAML_MIN_SEED_SHARE * rule.seeds
        rule.in_yaml = (rule.flyable and rule.manoeuvre not in dropped
                        and (majority or rule.manoeuvre == "direct"))
    _agreement(rules, analysis, facts, observations)
    return rules


def _holds(condition: dict, obs: np.ndarray, layout: Mapping[str, slice]) -> bool:
    name, _, index = condition["feature"].partition("[")
    value = float(obs[layout[name].start + (int(index.rstrip("]")) if index else 0)])
    limit = float(condition["value"])
    return {"<": value < limit, "<=": value <= limit, ">": value > limit, ">=": value >= limit,
            "==": value == limit, "!=": value != limit}[condition["op"]]


def _decide(chosen: list[CandidateRule], row: np.ndarray, layout: Mapping[str, slice]) -> int | None:
    """Index of the first rule whose conditions hold for `row` (None: none does)."""
    return next((k for k, rule in enumerate(chosen) if all(_holds(c, row, layout) for c in rule.when)), None)


def _recorded_steps(analysis: BehaviourAnalysis, observations: Observations):  # noqa: ANN202 - generator
    """(observation, the network's action) of every recorded step."""
    for episode in analysis.episodes:
        for d in episode.drones:
            obs = observations.get((episode.run, episode.episode, d.drone))
            if obs is not None:
                yield from zip(obs, d.actions, strict=False)


def _agreement(rules: list[CandidateRule], analysis: BehaviourAnalysis, facts: ScenarioFacts,
               observations: Observations) -> None:
    """Fill `agreement` of the YAML's rules over every recorded step (first matching rule)."""
    chosen = [r for r in rules if r.in_yaml]
    matched, agreed = [0] * len(chosen), [0] * len(chosen)
    for row, action in _recorded_steps(analysis, observations):
        k = _decide(chosen, row, facts.layout)
        if k is not None:
            matched[k] += 1
            agreed[k] += int(action == chosen[k].action)
    for k, rule in enumerate(chosen):
        rule.agreement = agreed[k] / matched[k] if matched[k] else None


def fidelity(document: dict, analysis: BehaviourAnalysis, facts: ScenarioFacts,
             observations: Observations) -> tuple[float | None, int]:
    """(share of the recorded steps at which the rules YAML picks the network's action, steps)."""
    chosen = [CandidateRule(manoeuvre="", text=r["text"], action=action_code(r["action"], document["frame"]),
                            action_name=r["action"], when=r.get("when", [])) for r in document["rules"]]
    same = total = 0
    for row, action in _recorded_steps(analysis, observations):
        k = _decide(chosen, row, facts.layout)
        total += 1
        same += int(k is not None and chosen[k].action == action)
    return (same / total if total else None), total


def rules_document(rules: list[CandidateRule], analysis: BehaviourAnalysis, facts: ScenarioFacts) -> dict:
    """The rules YAML (the format `eval --rules` flies) of the candidates marked `in_yaml`; always ends with an
    unconditional rule (toward the goal when `direct` had no support)."""
    kept = [r for r in rules if r.in_yaml]
    if not any(not r.when for r in kept):
        kept.append(CandidateRule(manoeuvre="direct", text="otherwise fly toward the goal (default: no "
                                  "direct flight supports it)", action=TOWARD_GOAL,
                                  action_name=action_name(TOWARD_GOAL, facts.frame)))
    split = analysis.split()
    return {
        "name": f"{Path(facts.file).stem} behaviour rules",
        "covers": [facts.file],
        "frame": facts.frame,
        "source": f"behaviour analysis of {analysis.scenario}: {len(analysis.runs)} seeds, "
                  f"{len(analysis.episodes)} episodes; {split_text(split) or 'no success'}",
        "rules": [{"text": r.text, **({"when": r.when} if r.when else {}), "action": r.action_name,
                   "support": {"seeds": r.support_seeds, "episodes": r.support_episodes}} for r in kept],
    }


def write_rules_yaml(path: str | Path, document: dict) -> Path:
    """Write a rules document as YAML (readable back with `errors.load_yaml`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(document, sort_keys=False, allow_unicode=True, width=100), encoding="utf-8")
    return path


@dataclass
class ThesisCheck:
    """One of the thesis's rules 0-5 checked on the classifications."""

    rule: int
    text: str
    applicable: bool
    recovered: bool | None = None
    """Held in more than half of the seeds (None: not applicable, or nothing to judge by)."""
    support_seeds: int = 0
    seeds: int = 0
    support_episodes: int = 0
    episodes: int = 0
    units: str = ""
    """What `episodes` counts (`successful head-on episodes`)."""
    evidence: str = ""
    """What `support_episodes` counts among them (`with both passing right`), or why not applicable."""

    def line(self) -> str:
        head = f"rule {self.rule} ({self.text}):"
        if not self.applicable:
            return f"{head} not applicable here: {self.evidence}"
        if self.recovered is None:
            return f"{head} no evidence in {self.seeds} seeds: no {self.units}"
        verdict = "recovered" if self.recovered else "not recovered"
        return (f"{head} {verdict}: held in {self.support_seeds} of {self.seeds} seeds; "
                f"{self.support_episodes} of {self.episodes} {self.units} {self.evidence}")

    def to_dict(self) -> dict:
        return {**asdict(self), "line": self.line()}


THESIS_RULES = (
    "don't fly too fast toward the ground",
    "use the planner's path when safe",
    "fly over a lone static obstacle",
    "head-on: both move to their right",
    "go through an opening big enough",
    "two drones at one opening: the lower priority hovers until the other has passed",
)


def _per_seed(analysis: BehaviourAnalysis, rule: int, units: str, evidence: str, select, held,  # noqa: ANN001
              share: float = SEED_SUPPORT_SHARE) -> ThesisCheck:
    """A check over the items `select(run)` of every run (drone-episodes or episodes) that hold
    when `held(item)`; the rule holds in a seed when at least `share` of its items do."""
    check = ThesisCheck(rule, THESIS_RULES[rule], True, seeds=len(analysis.runs), units=units, evidence=evidence)
    for run in analysis.runs:
        items = select(run)
        good = sum(bool(held(item)) for item in items)
        check.support_episodes += good
        check.episodes += len(items)
        check.support_seeds += bool(items) and good >= share * len(items)
    check.recovered = check.support_seeds * 2 > check.seeds if check.episodes else None
    return check


def thesis_checks(analysis: BehaviourAnalysis, facts: ScenarioFacts) -> list[ThesisCheck]:
    """The thesis's rules 0-5 as recovered / not recovered / not applicable, with support."""
    def not_applicable(rule: int, why: str) -> ThesisCheck:
        return ThesisCheck(rule, THESIS_RULES[rule], False, seeds=len(analysis.runs), evidence=why)

    checks = [_per_seed(analysis, 0, "drone-episodes", "without a ground crash (descent is capped at the "
                        "action speed)", lambda r: r.drone_episodes,
                        lambda d: not (d.outcome == "crash" and (d.end_altitude_m or 0.0) < GROUND_CRASH_M))]

    if facts.num_drones == 1 and not facts.lone_obstacle and not facts.opening:
        checks.append(_per_seed(analysis, 1, "direct flights",
                                f"using action 6 in at least {PLANNER_SHARE:.0%} of their steps",
                                lambda r: [d for d in r.drone_episodes if d.manoeuvre == "direct"],
                                lambda d: d.planner_share >= PLANNER_SHARE))
    else:
        checks.append(not_applicable(1, "the straight path is not always safe here (obstacles or other drones)"))

    if facts.num_drones == 1 and facts.lone_obstacle:
        checks.append(_per_seed(analysis, 2, "successful drone-episodes", "climbing over",
                                lambda r: [d for d in r.drone_episodes if d.outcome == "goal"],
                                lambda d: d.manoeuvre == "climb_over"))
    else:
        checks.append(not_applicable(2, "no lone static obstacle with a single drone"))

    if any(e.head_on for e in analysis.episodes) and not facts.opening:  # at an opening: rule 5
        mirrored = sum(e.success and e.head_on and all(d.manoeuvre == "pass_left" for d in e.drones)
                       for e in analysis.episodes)
        checks.append(_per_seed(analysis, 3, "successful head-on episodes",
                                f"with both passing right ({mirrored} both left)",
                                lambda r: [e for e in r.episodes if e.success and e.head_on],
                                lambda e: all(d.manoeuvre == "pass_right" for d in e.drones)))
    else:
        checks.append(not_applicable(3, "no head-on encounter in open space"))

    if facts.opening:
        checks.append(_per_seed(analysis, 4, "drone-episodes", "through the opening to the goal",
                                lambda r: r.drone_episodes, lambda d: d.outcome == "goal"))
    else:
        checks.append(not_applicable(4, "no opening"))

    if facts.opening and facts.num_drones > 1:
        # The order is what the rule is for; how the second drone waits (hovering, backing off,
        # or a climb or sidestep no hover step shows) is the evidence's detail. One drone goes
        # first anyway, so a seed holds only when the order follows priority well above chance.
        ordered = [e for e in analysis.episodes if e.success and e.order_follows_priority]
        hovers = sum(e.shows("yield_hover") for e in ordered)
        backs = sum(e.shows("yield_back_off") for e in ordered)
        checks.append(_per_seed(analysis, 5, "successful episodes",
                                f"where the lower-priority drone went through the opening second ({hovers} of "
                                f"them hovering, {backs} backing off while the other passed)",
                                lambda r: [e for e in r.episodes if e.success and e.order_follows_priority is not None],
                                lambda e: e.order_follows_priority, share=ORDER_SEED_SHARE))
    else:
        checks.append(not_applicable(5, "not two drones at an opening"))
    return checks
