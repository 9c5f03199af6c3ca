"""Rule sets as scripted policies: a small YAML of condition -> action rules, flown like a network.

A rule set (written by hand, by behaviour analysis or by tree distillation) names its actions
in an action frame and tests observation features by name:

```yaml
name: climb over the block
covers: [obstacle.yaml]            # scenario files it claims to solve
frame: world                       # the frame its action names are in (world | goal)
rules:                             # the first rule whose conditions all hold wins
  - text: "block ahead within 3 m: climb"
    when: [{feature: "lidar[17]", op: "<", value: 3.0}]
    action: up                     # a name in `frame` or a code 0..7
    support: {seeds: 9, episodes: 412}   # optional
  - text: "otherwise fly toward the goal"
    action: toward goal            # no `when`: always holds
```

`load_rules` checks the file on its own (keys, ops, feature names, action names); `bind` checks it
against one scenario (the feature exists in its observation, the index is in range, the action
frame matches) and gives a `RulePolicy(obs) -> action`. When no rule holds the drone hovers.
A rule set whose actions are all frame-independent (4 down, 5 up, 6 toward goal, 7 hover) flies
in either frame; one that uses 0-3 only in its own. Evaluation goes through
`rl.evaluation.evaluate.evaluate_in_world`, so the rates are computed exactly as for learned policies.
"""

from __future__ import annotations

import operator
import os
import re
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sitl_bridge.envs.features import FEATURES, observation_layout
from sitl_bridge.envs.scenario import Scenario, load_scenario
from sitl_bridge.envs.task import ACTION_FRAMES
from sitl_bridge.errors import ConfigError, Node, load_yaml
from sitl_bridge.rl.common.action_names import ACTION_NAMES_BY_FRAME, action_code, action_name
from sitl_bridge.rl.evaluation.evaluate import EvalResult, evaluate_in_world
from sitl_bridge.rl.evaluation.rollout import Trace
from sitl_bridge.world.lookup import resolve_world

OPS: dict[str, Callable[[float, float], bool]] = {
    "<": operator.lt, "<=": operator.le, ">": operator.gt, ">=": operator.ge, "==": operator.eq, "!=": operator.ne,
}
NUM_ACTIONS = len(ACTION_NAMES_BY_FRAME["world"])
FRAME_DEPENDENT = frozenset({0, 1, 2, 3})
"""The horizontal moves: their meaning turns with the frame (north vs forward)."""
HOVER = 7
"""What a drone does when no rule holds."""

_FEATURE = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*(?:@\d+)?)\s*(?:\[\s*(\d+)\s*\])?\s*$")
"""`NAME[INDEX]` or `NAME`; NAME may carry `@N`, the layout's key of a feature listed N times."""


@dataclass(frozen=True)
class Condition:
    """`feature op value`, e.g. `lidar[17] < 3.0`; `index` None for a size-1 feature named bare."""

    feature: str
    name: str
    index: int | None
    op: str
    value: float
    path: str
    """Key path of the condition in its file (`rules[0].when[1]`), for errors."""

    def holds(self, x: float) -> bool:
        return OPS[self.op](float(x), self.value)

    def __str__(self) -> str:
        return f"{self.feature} {self.op} {self.value:g}"


@dataclass(frozen=True)
class Rule:
    """Conditions that must all hold (none: always) and the action taken then."""

    text: str
    conditions: tuple[Condition, ...]
    action: int
    path: str
    support: dict[str, int] | None = None


@dataclass(frozen=True)
class RuleSet:
    """A parsed rule file, not yet tied to a scenario."""

    name: str
    covers: tuple[str, ...]
    frame: str
    rules: tuple[Rule, ...]
    source: str
    """The file it was read from (the prefix of every error)."""
    origin: str | None = None
    """The file's `source:` text: where the rules came from."""

    def describe(self) -> str:
        """The rules as numbered if-then lines, actions named in the rule set's frame."""
        lines = [f"{self.name} ({self.frame} frame)"]
        for i, rule in enumerate(self.rules):
            when = " and ".join(map(str, rule.conditions)) or "always"
            lines.append(f"  {i}. if {when}: {action_name(rule.action, self.frame)}  ({rule.text})")
        return "\n".join(lines)


def parse_feature(text: str) -> tuple[str, int | None] | None:
    """`lidar[17]` -> ("lidar", 17), `own_priority` -> ("own_priority", None),
    `dummy@2[0]` -> ("dummy@2", 0); None if malformed."""
    match = _FEATURE.match(text)
    if match is None:
        return None
    return match.group(1), None if match.group(2) is None else int(match.group(2))


def _condition(node: Node) -> Condition:
    node.reject_unknown({"feature", "op", "value"})
    feature_node = node.get("feature")
    text = feature_node.string()
    parsed = parse_feature(text)
    if parsed is None or parsed[0].split("@")[0] not in FEATURES:
        raise feature_node.error(f"NAME[INDEX] or NAME with NAME an observation feature ({', '.join(FEATURES)})")
    op = node.get("op").string(tuple(OPS))
    value = node.get("value").number()
    return Condition(text.strip(), parsed[0], parsed[1], op, value, node.path)


def _action(node: Node, frame: str) -> int:
    value = node.value
    if isinstance(value, int) and not isinstance(value, bool):
        return node.integer(minimum=0, maximum=NUM_ACTIONS - 1)
    if isinstance(value, str):
        try:
            return action_code(value.strip(), frame)
        except ValueError:
            pass
    names = ", ".join(ACTION_NAMES_BY_FRAME[frame])
    raise node.error(f"an action of the {frame} frame ({names}) or a code 0..{NUM_ACTIONS - 1}")


def _support(node: Node) -> dict[str, int] | None:
    if node.value is None:
        return None
    node.reject_unknown({"seeds", "episodes"})
    return {key: child.integer(minimum=0) for key, child in node.items()}


def _rule(node: Node, frame: str) -> Rule:
    node.reject_unknown({"text", "when", "action", "support"})
    when = node.get("when", None)
    conditions = () if when.value is None else tuple(_condition(c) for c in when.list())
    action = _action(node.get("action"), frame)
    default_text = " and ".join(map(str, conditions)) or "always"
    text = node.get("text", f"{default_text}: {action_name(action, frame)}").string()
    return Rule(text, conditions, action, node.path, _support(node.get("support", None)))


def parse_rules(root: Node) -> RuleSet:
    """A rule set from a read YAML root node; every mistake is a one-line ConfigError."""
    if root.value is None:
        raise ConfigError(f"{root.source}: empty file (expected a mapping with `frame:` and `rules:`)")
    root.reject_unknown({"name", "covers", "frame", "source", "rules"})
    frame = root.get("frame").string(ACTION_FRAMES)
    origin = root.get("source", None)
    return RuleSet(
        name=root.get("name", Path(root.source).stem).string(),
        covers=tuple(item.string() for item in root.get("covers", []).list()),
        frame=frame,
        rules=tuple(_rule(item, frame) for item in root.get("rules").list(min_len=1)),
        source=root.source,
        origin=None if origin.value is None else origin.string(),
    )


def load_rules(path: str | Path) -> RuleSet:
    """Read and check a rule file on its own (see `bind` for the checks against a scenario)."""
    return parse_rules(load_yaml(path))


@dataclass
class RulePolicy:
    """A rule set bound to one scenario's observation layout: call it with one observation."""

    rules: RuleSet
    columns: tuple[tuple[int, ...] | None, ...]
    """Per rule, the observation column each of its conditions reads; None for a rule left out
    here (it tests a feature this scenario does not observe, see `bind`): it never holds."""
    obs_dim: int
    fired: list[int] = field(default_factory=list)
    """How often each rule decided (last entry: no rule held, hovered), since creation."""

    def __post_init__(self) -> None:
        self.fired = [0] * (len(self.rules.rules) + 1)

    @property
    def left_out(self) -> tuple[int, ...]:
        """Indices of the rules left out here (see `columns`)."""
        return tuple(i for i, columns in enumerate(self.columns) if columns is None)

    def choose(self, obs: np.ndarray) -> int:
        """Index of the first rule whose conditions all hold (len(rules) when none does)."""
        for i, (rule, columns) in enumerate(zip(self.rules.rules, self.columns, strict=True)):
            if columns is not None and all(c.holds(obs[col]) for c, col in zip(rule.conditions, columns,
                                                                               strict=True)):
                return i
        return len(self.rules.rules)

    def __call__(self, obs: np.ndarray) -> int:
        obs = np.asarray(obs, dtype=np.float64).reshape(-1)
        if obs.shape[0] != self.obs_dim:
            raise ValueError(f"{self.rules.source}: bound to {self.obs_dim} observation values, got {obs.shape[0]}")
        i = self.choose(obs)
        self.fired[i] += 1
        return self.rules.rules[i].action if i < len(self.rules.rules) else HOVER

    def fired_share(self) -> dict[str, float]:
        """Share of decisions per rule (`"0: <text>"`, ..., `"none: hover"`)."""
        total = sum(self.fired) or 1
        names = [f"{i}: {r.text}" for i, r in enumerate(self.rules.rules)] + ["none: hover"]
        return {name: count / total for name, count in zip(names, self.fired, strict=True)}


def _column(condition: Condition, layout: dict[str, slice], scenario: Scenario, source: str) -> int:
    where = f"{source}: {condition.path}.feature"
    block = layout.get(condition.name)
    if block is None:
        have = ", ".join(f"{name}[0..{s.stop - s.start - 1}]" for name, s in layout.items())
        raise ConfigError(f"{where}: expected a feature of the observation of {scenario.task.source} "
                          f"({have}), got {condition.feature!r}")
    size = block.stop - block.start
    if condition.index is None:
        if size != 1:
            raise ConfigError(f"{where}: expected {condition.name}[INDEX] ({condition.name} has {size} values "
                              f"in {scenario.task.source}), got {condition.feature!r}")
        return block.start
    if condition.index >= size:
        raise ConfigError(f"{where}: expected an index 0..{size - 1} of {condition.name} in "
                          f"{scenario.task.source}, got {condition.feature!r}")
    return block.start + condition.index


def bind(rules: RuleSet, scenario: Scenario, *, leave_out_absent: bool = False) -> RulePolicy:
    """The rule set as a policy for `scenario`; a feature it lacks, an index out of range or a
    frame mismatch (for a rule with a frame-dependent action) is a one-line ConfigError.

    With `leave_out_absent`, a rule testing a feature that `scenario` does not observe at all
    (another drone's position in a one-drone scenario) is left out there instead (it never holds:
    `RulePolicy.left_out`), so a traffic rule set can be flown in the simpler scenarios before it."""
    frame = scenario.task.action.frame
    if frame != rules.frame:
        for rule in rules.rules:
            if rule.action in FRAME_DEPENDENT:
                raise ConfigError(
                    f"{rules.source}: frame: expected {frame} (the action frame of {scenario.task.source}; "
                    f"{rule.path}.action {action_name(rule.action, rules.frame)!r} depends on it), "
                    f"got {rules.frame!r}")
    layout = observation_layout(scenario.task.observation)
    columns = tuple(None if leave_out_absent and any(c.name not in layout for c in rule.conditions) else
                    tuple(_column(c, layout, scenario, rules.source) for c in rule.conditions)
                    for rule in rules.rules)
    return RulePolicy(rules, columns, scenario.task.observation_size)


def rule_policy(rules: str | Path | RuleSet, world: str | Path, *, leave_out_absent: bool = False) -> RulePolicy:
    """Load (if a path) and bind a rule set to the scenario file `world` (see `bind`)."""
    rule_set = rules if isinstance(rules, RuleSet) else load_rules(rules)
    return bind(rule_set, load_scenario(world), leave_out_absent=leave_out_absent)


def covered_scenarios(rules: RuleSet) -> list[Path]:
    """The scenario files of `covers`: next to the rule file, else a shipped world name. A rules
    file named like the scenario it covers (`rules/empty.yaml` covering `empty.yaml`) is not its
    own scenario."""
    here = Path(rules.source).parent
    itself = Path(rules.source).resolve()
    paths = []
    for i, name in enumerate(rules.covers):
        local = here / name
        try:
            paths.append(local if local.is_file() and local.resolve() != itself else resolve_world(name))
        except ConfigError as exc:
            raise ConfigError(f"{rules.source}: covers[{i}]: expected a scenario file, got {name!r} "
                              f"({str(exc).split(': ', 1)[-1]})") from None
    return paths


def cover_name(world: str | Path, folder: str | Path) -> str:
    """How a rules file in `folder` names the scenario file `world` under `covers` so that
    `covered_scenarios` finds it again: its bare name when that is this very file (a shipped
    world), else its path relative to `folder`."""
    world = Path(world).resolve()
    try:
        if resolve_world(world.name).resolve() == world:
            return world.name
    except ConfigError:
        pass
    return os.path.relpath(world, Path(folder).resolve())


def evaluate_rules(rules: str | Path | RuleSet, world: str | Path, *, episodes: int, autopilot: str = "direct",
                   seed: int = 0, progress: bool = False,
                   video_dir: str | Path | None = None) -> tuple[EvalResult, list[Trace], RulePolicy]:
    """Fly a rule set greedily in `world` on the evaluation seeds (`sitl-bridge eval --rules`)."""
    policy = rule_policy(rules, world)
    result, traces = evaluate_in_world(policy, world, episodes=episodes, autopilot=autopilot, seed=seed,
                                       progress=progress, video_dir=video_dir)
    return result, traces, policy


def verify_rules(rules_path: str | Path, scenarios: Iterable[str | Path] = (), episodes: int = 20,
                 seed: int = 0, *, autopilot: str = "direct", progress: bool = False) -> dict[str, dict[str, Any]]:
    """Fly a rule set in every scenario it `covers` and in `scenarios` (the simpler ones before
    them): per scenario (keyed by file stem) the evaluation's keys plus `success`,
    `collision_rate`, `covered`, `rules_fired` and `rules_left_out` (the texts of the rules that
    test a feature an extra scenario does not observe: left out there, see `bind`). A covered
    scenario the rules cannot be flown in is an error; an extra one is reported as
    `{"skipped": reason}`."""
    rules = load_rules(rules_path)
    plan: dict[Path, bool] = {path.resolve(): True for path in covered_scenarios(rules)}
    for scenario in scenarios:
        plan.setdefault(resolve_world(scenario).resolve(), False)
    out: dict[str, dict[str, Any]] = {}
    for path, covered in plan.items():
        key = path.stem if path.stem not in out else str(path)
        try:
            policy = rule_policy(rules, path, leave_out_absent=not covered)
        except ConfigError as exc:
            if covered:
                raise
            out[key] = {"scenario": str(path), "covered": False, "skipped": str(exc)}
            continue
        result, _ = evaluate_in_world(policy, path, episodes=episodes, autopilot=autopilot, seed=seed,
                                      progress=progress)
        out[key] = {"scenario": str(path), "covered": covered, **result.to_dict(),
                    "success": result.success_rate, "collision_rate": result.crash_rate,
                    "rules_fired": policy.fired_share(),
                    "rules_left_out": [rules.rules[i].text for i in policy.left_out]}
    return out
