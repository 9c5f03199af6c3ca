"""Behaviour analysis: greedy episodes classified into named manoeuvres from their trajectories.

Every drone-episode gets one manoeuvre (the first that applies, in `PRECEDENCE` order) plus tags
for every other one that also applies, and its outcome:

| manoeuvre | what the path shows |
|---|---|
| `yield_back_off` | moves back along its travel direction while another drone near it is under way |
| `yield_hover` | hovers while another drone near it is under way (the thesis's TW "one hovers") |
| `oscillation` | repeated back-and-forth: reversals of direction between consecutive moves |
| `to_opening` | climbs (or sinks) toward a wall's opening before going through it (the thesis's W "5 5 5 5 3 3 3") |
| `climb_over` | rises clearly above start and goal (the thesis's O "fly over") |
| `dive_under` | drops clearly below start and goal (passes under another drone or an obstacle) |
| `pass_left` / `pass_right` | leaves the straight start-goal line to the left / right of its own travel direction |
| `hover` | hovers most of the episode with nobody passing (stalls) |
| `direct` | none of the above: the straight path (`planner_share`: share of action 6, the planner's) |

Episodes are grouped so a multi-drone episode sees every drone: yields need the other drone's
path, and each yield is checked against the scenario's priority rule (`envs/priority.py`).
Where drones share an opening (a wall's window: `openings`), the order in which they go through
it is checked against the same rule too: a yield can be a climb or a sidestep that no hover/back
step shows, but the lower-priority drone still goes second.
Across runs (seeds) the counts are kept per seed; a behaviour that does not dominate is reported
as a split ("pass_right 60 %, pass_left 40 %"), never silently as the winner.
"""

from __future__ import annotations

import math
from collections import Counter, defaultdict
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sitl_bridge.envs.features import travel_frame
from sitl_bridge.envs.priority import priorities
from sitl_bridge.rl.analysis.behaviour_summary import CLIMB_OVER_M, SIDESTEP_M, path_geometry
from sitl_bridge.rl.evaluation.rollout import Trace

CONTINUOUS_ACTIONS = ("continuous velocity actions: behaviour classes, rules and distilled trees read the "
                      "discrete action codes (a continuous policy's manoeuvres are not classified yet)")
"""Why a scenario with `task.action.type: velocity` is left out of the analyses built on codes."""


def why_not_classified(world: str | Path) -> str | None:
    """Why the greedy episodes of scenario file `world` cannot be classified (None: they can)."""
    from sitl_bridge.envs.scenario import load_scenario

    return CONTINUOUS_ACTIONS if load_scenario(world).task.action.continuous else None

MOVE_M = 0.5
"""A step displacing this much moves (one 1 m/s action for 1 s flies about 1 m)."""
HOVER_M = 0.3
"""A step displacing less than this hovers (hover drift and the slowed final toward-goal step stay
below it, a moving action is far above)."""
BACK_M = 0.5
"""A step losing this much along the own travel direction moves back (half a moving action)."""
ADVANCE_M = 0.5
"""Another drone whose distance to its own goal shrinks this much in a step is under way."""
YIELD_RADIUS_M = 6.0
"""Waiting counts as yielding only while the other drone is this close: TE's and TW's drones start
10 m and 8 m apart, so waiting at the start counts once the other has closed in."""
YIELD_MIN_STEPS = 2
"""Hover/back steps while the other passes needed for a yield: one 1 s hover is often greedy
dithering; two seconds of waiting while the other moves is a decision."""
REVERSAL_COS = -0.5
"""Consecutive moves more than 120 degrees apart reverse the direction."""
OSCILLATION_REVERSALS = 3
"""Reversals for oscillation: a back-off and the return already make two; a third is back-and-forth."""
HOVER_SHARE = 0.5
"""A drone hovering in at least this share of its steps (nobody passing) stalls (`hover`)."""
DOMINANT_SHARE = 0.8
"""A manoeuvre with this share of the successful drone-episodes dominates; below it the report
is a split."""
HEAD_ON_COS = -0.9
"""Two drones whose horizontal travel directions are this close to opposite fly head-on."""

PRECEDENCE = ("yield_back_off", "yield_hover", "oscillation", "to_opening", "climb_over", "dive_under", "pass_left",
              "pass_right", "hover", "direct")
"""Manoeuvre names, most specific first: the first that applies names a drone-episode."""


@dataclass
class DroneBehaviour:
    """One drone's episode, classified."""

    drone: int
    manoeuvre: str
    outcome: str
    steps: int
    tags: list[str] = field(default_factory=list)
    """Every manoeuvre that applies (the named one included)."""
    trigger_step: int | None = None
    """Step at which the named manoeuvre starts (the observation before it triggers a rule)."""
    action: int | None = None
    """Most common action code during the manoeuvre's steps."""
    planner_share: float = 0.0
    """Share of action 6 (toward goal: the thesis's trajectory planner)."""
    climb_m: float = 0.0
    lateral_m: float = 0.0
    """Largest sideways distance from the start-goal line; positive = left of travel direction."""
    reversals: int = 0
    yield_steps: int = 0
    yielded_to: int | None = None
    priority: float | None = None
    """Own priority (`envs/priority.py`) when it yielded; the one it yielded to is in `other_priority`."""
    other_priority: float | None = None
    end_altitude_m: float | None = None
    opening_step: int | None = None
    """Steps it flew until it was through the shared opening (None: never, or no opening)."""
    actions: list[int] = field(default_factory=list, repr=False)

    def to_dict(self) -> dict:
        out = {k: v for k, v in vars(self).items() if k != "actions"}
        return out


@dataclass
class EpisodeBehaviour:
    """All drones of one episode."""

    run: str
    episode: int
    seed: int
    drones: list[DroneBehaviour]
    head_on: bool = False
    """Two drones fly opposite travel directions (the thesis's TE)."""
    order_follows_priority: bool | None = None
    """Every drone went through the shared opening after every drone of higher priority (None:
    fewer than two drones went through one)."""

    @property
    def success(self) -> bool:
        """Every drone reached its goal."""
        return all(d.outcome == "goal" for d in self.drones)

    @property
    def pattern(self) -> str:
        """The drones' manoeuvres, sorted: `pass_right+pass_right`."""
        return "+".join(sorted(d.manoeuvre for d in self.drones))

    @property
    def yielders(self) -> list[DroneBehaviour]:
        return [d for d in self.drones if d.manoeuvre.startswith("yield_")]

    @property
    def follows_priority(self) -> bool | None:
        """Every yielding drone has lower priority than the one it yielded to (None: no yield)."""
        yielders = self.yielders
        if not yielders:
            return None
        return all(d.priority is not None and d.other_priority is not None and d.priority < d.other_priority
                   for d in yielders)

    def shows(self, manoeuvre: str) -> bool:
        return any(d.manoeuvre == manoeuvre for d in self.drones)


@dataclass(frozen=True)
class Opening:
    """A wall's window as a plane: a drone is through it once it changes side of the wall."""

    center_enu_m: tuple[float, float, float]
    normal_enu: tuple[float, float, float]
    """Unit normal of the wall (its thickness axis)."""

    def side(self, position: np.ndarray) -> float:
        return float((np.asarray(position) - self.center_enu_m) @ np.asarray(self.normal_enu))


def openings(obstacles: Iterable) -> tuple[Opening, ...]:  # noqa: ANN001 - world.schema.Obstacle
    """The openings of a world's static walls (`world.obstacles`)."""
    found = []
    for obstacle in obstacles:
        shape, window = obstacle.shape, obstacle.shape.opening
        if obstacle.dynamic or window is None or shape.size_m is None:
            continue
        c, s = math.cos(obstacle.yaw_rad), math.sin(obstacle.yaw_rad)
        x, y, z = obstacle.position_m
        height = z - shape.size_m[2] / 2 + window.bottom_m + window.height_m / 2
        found.append(Opening((x + c * window.offset_m, y + s * window.offset_m, height), (-s, c, 0.0)))
    return tuple(found)


def _through_step(path: np.ndarray, goal: np.ndarray, opening: Opening) -> int | None:
    """Steps a drone whose goal is across `opening`'s wall flew until it was on the goal's side."""
    start, target = opening.side(path[0]), opening.side(goal)
    if start * target >= 0:
        return None
    return next((t for t in range(1, len(path)) if opening.side(path[t]) * start < 0), None)


def _order_follows_priority(drones: list[DroneBehaviour], ranks: np.ndarray) -> bool | None:
    through = [(d.opening_step, float(ranks[i])) for i, d in enumerate(drones) if d.opening_step is not None]
    if len(through) < 2:
        return None
    return all(step_a < step_b for step_a, rank_a in through for step_b, rank_b in through if rank_a > rank_b)


def _steps(path: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """Per-step displacements in the travel frame (right, forward, up)."""
    return np.diff(path, axis=0) @ rotation.T


def _reversals(moves: np.ndarray) -> tuple[int, int | None]:
    """Direction reversals between consecutive moving steps, and the step of the first."""
    moving = [(t, d) for t, d in enumerate(moves) if np.linalg.norm(d) >= MOVE_M]
    count, first = 0, None
    for (_, a), (t, b) in zip(moving, moving[1:], strict=False):
        if float(a @ b) < REVERSAL_COS * float(np.linalg.norm(a) * np.linalg.norm(b)):
            count += 1
            first = t if first is None else first
    return count, first


def _modal(actions: list[int], steps: list[int]) -> int | None:
    chosen = [actions[t] for t in steps if t < len(actions)]
    return Counter(chosen).most_common(1)[0][0] if chosen else None


def _yield(i: int, paths: list[np.ndarray], goals: list[np.ndarray], moves: np.ndarray,
           ) -> tuple[list[int], int, Counter]:
    """Steps at which drone i hovered or moved back while another drone near it was under way,
    how many of them moved back, and whom it waited for (drone -> steps)."""
    steps, back, towards = [], 0, Counter()
    for t, move in enumerate(moves):
        hovering = float(np.linalg.norm(move)) < HOVER_M
        backing = move[1] <= -BACK_M
        if not (hovering or backing):
            continue
        passing = [j for j in range(len(paths)) if j != i and t + 1 < len(paths[j])
                   and np.linalg.norm(paths[j][t] - goals[j]) - np.linalg.norm(paths[j][t + 1] - goals[j]) >= ADVANCE_M
                   and np.linalg.norm(paths[i][t] - paths[j][t]) <= YIELD_RADIUS_M]
        if passing:
            steps.append(t)
            back += int(backing)
            towards.update(passing)
    return steps, back, towards


def classify_episode(traces: list[Trace], *, run: str = "", priority_rule: str = "lower_coordinate_yields",
                     shared_openings: tuple[Opening, ...] = ()) -> EpisodeBehaviour:
    """Classify every drone of one episode (`traces`: that episode's traces, one per drone);
    `shared_openings` (`openings(world.obstacles)`) adds the order they went through them and
    names the climbs to an opening's height (`to_opening`)."""
    traces = sorted(traces, key=lambda t: t.drone)
    usable = all(len(t.positions_enu_m) >= 2 and t.goal_enu_m is not None for t in traces)
    paths = [np.asarray(t.positions_enu_m, dtype=float).reshape(-1, 3) for t in traces]
    goals = [np.asarray(t.goal_enu_m if t.goal_enu_m is not None else [0, 0, 0], dtype=float) for t in traces]
    drones = []
    for i, trace in enumerate(traces):
        drone = DroneBehaviour(drone=trace.drone, manoeuvre="unknown", outcome=trace.outcome, steps=trace.steps,
                               actions=list(trace.actions),
                               planner_share=trace.actions.count(6) / trace.steps if trace.steps else 0.0,
                               end_altitude_m=float(paths[i][-1, 2]) if len(paths[i]) else None)
        if usable:
            _classify_drone(drone, i, trace, paths, goals, priority_rule, shared_openings)
        drones.append(drone)
    episode = EpisodeBehaviour(run=run, episode=traces[0].episode if traces else 0,
                               seed=traces[0].seed if traces else 0, drones=drones)
    if usable and len(traces) > 1:
        directions = [travel_frame(p[0], g)[1, :2] for p, g in zip(paths, goals, strict=True)]
        episode.head_on = any(float(a @ b) <= HEAD_ON_COS for k, a in enumerate(directions)
                              for b in directions[k + 1:])
        _passing_order(episode, paths, goals, priority_rule, shared_openings)
    return episode


def _passing_order(episode: EpisodeBehaviour, paths: list[np.ndarray], goals: list[np.ndarray],
                   priority_rule: str, shared_openings: tuple[Opening, ...]) -> None:
    """Who went through the first opening that two or more drones went through, and whether in
    priority order (priority as it stood at the start: the rule's fixed ranks in TW)."""
    for opening in shared_openings:
        steps = [_through_step(path, goal, opening) for path, goal in zip(paths, goals, strict=True)]
        if sum(s is not None for s in steps) < 2:
            continue
        for drone, step in zip(episode.drones, steps, strict=True):
            drone.opening_step = step
        ranks = priorities(priority_rule, [p[0] for p in paths], [p[0] for p in paths], goals)
        episode.order_follows_priority = _order_follows_priority(episode.drones, ranks)
        return


def _height_to_opening(path: np.ndarray, goal: np.ndarray, moves: np.ndarray,
                       wall_openings: tuple[Opening, ...]) -> list[int]:
    """Steps that climbed (or sank) toward the height of the opening the drone went through,
    before it was through, more up (down) than along; empty unless they changed its height by at
    least CLIMB_OVER_M. A slanting step toward a goal higher up is direct flight, not this."""
    for opening in wall_openings:
        through = _through_step(path, goal, opening)
        if through is None:
            continue
        sign = 1.0 if opening.center_enu_m[2] >= path[0, 2] else -1.0
        steps = [t for t in range(through)
                 if sign * moves[t][2] >= max(MOVE_M, float(np.linalg.norm(moves[t][:2])))]
        if sum(sign * moves[t][2] for t in steps) >= CLIMB_OVER_M:
            return steps
    return []


def _classify_drone(drone: DroneBehaviour, i: int, trace: Trace, paths: list[np.ndarray],
                    goals: list[np.ndarray], priority_rule: str, wall_openings: tuple[Opening, ...] = ()) -> None:
    path = paths[i]
    moves = _steps(path, travel_frame(path[0], goals[i]))
    geometry = path_geometry(trace)
    assert geometry is not None  # usable: positions and goal present
    drone.climb_m, drone.lateral_m = geometry.climb_above_m, geometry.lateral_m
    drone.reversals, first_reversal = _reversals(moves)
    yield_steps, back, towards = _yield(i, paths, goals, moves)
    drone.yield_steps = len(yield_steps)
    hover_steps = [t for t, m in enumerate(moves) if np.linalg.norm(m) < HOVER_M]

    found: dict[str, tuple[int | None, list[int]]] = {}  # manoeuvre -> (trigger step, its steps)
    if len(yield_steps) >= YIELD_MIN_STEPS:
        kind = "yield_back_off" if back else "yield_hover"
        found[kind] = (yield_steps[0], yield_steps)
    if drone.reversals >= OSCILLATION_REVERSALS:
        found["oscillation"] = (first_reversal, [])
    to_opening = _height_to_opening(path, goals[i], moves, wall_openings)
    if to_opening:
        found["to_opening"] = (to_opening[0], to_opening)
    if drone.climb_m >= CLIMB_OVER_M:
        rising = [t for t, m in enumerate(moves) if m[2] >= MOVE_M]
        found["climb_over"] = (rising[0] if rising else None, rising)
    drop_m = float(min(path[0, 2], goals[i][2]) - path[:, 2].min())
    if drop_m >= CLIMB_OVER_M:  # the same clearance as a climb, downwards
        sinking = [t for t, m in enumerate(moves) if m[2] <= -MOVE_M]
        found["dive_under"] = (sinking[0] if sinking else None, sinking)
    if abs(drone.lateral_m) >= SIDESTEP_M:
        sign = 1.0 if drone.lateral_m > 0 else -1.0  # right is +x of the travel frame, left is -x
        side = [t for t, m in enumerate(moves) if -sign * m[0] >= MOVE_M]
        found["pass_left" if sign > 0 else "pass_right"] = (side[0] if side else None, side)
    if "yield_hover" not in found and "yield_back_off" not in found and moves.shape[0] \
            and len(hover_steps) >= HOVER_SHARE * moves.shape[0]:
        found["hover"] = (hover_steps[0], hover_steps)
    found["direct"] = (0, list(range(moves.shape[0])))

    drone.tags = [name for name in PRECEDENCE if name in found]
    drone.manoeuvre = drone.tags[0]
    drone.trigger_step, steps = found[drone.manoeuvre]
    drone.action = _modal(trace.actions, steps)
    if drone.manoeuvre.startswith("yield_") and towards:
        other = towards.most_common(1)[0][0]
        t = yield_steps[0]
        ranks = priorities(priority_rule, [p[0] for p in paths], [p[min(t, len(p) - 1)] for p in paths], goals)
        drone.yielded_to = other
        drone.priority, drone.other_priority = float(ranks[i]), float(ranks[other])


def classify(traces: list[Trace], *, run: str = "", priority_rule: str = "lower_coordinate_yields",
             shared_openings: tuple[Opening, ...] = ()) -> list[EpisodeBehaviour]:
    """Classify rollouts (`rl.evaluation.rollout.rollout`'s traces), grouped per episode."""
    by_episode: dict[int, list[Trace]] = defaultdict(list)
    for trace in traces:
        by_episode[trace.episode].append(trace)
    return [classify_episode(by_episode[e], run=run, priority_rule=priority_rule, shared_openings=shared_openings)
            for e in sorted(by_episode)]


def split_text(shares: dict[str, float]) -> str:
    """`pass_right 60 %, pass_left 40 %` (largest first)."""
    return ", ".join(f"{name} {share:.0%}".replace("%", " %") for name, share in
                     sorted(shares.items(), key=lambda kv: (-kv[1], kv[0])))


def _shares(counter: Counter) -> dict[str, float]:
    total = sum(counter.values())
    return {k: v / total for k, v in sorted(counter.items(), key=lambda kv: (-kv[1], kv[0]))} if total else {}


@dataclass
class RunBehaviour:
    """The classified greedy episodes of one run (one training seed)."""

    label: str
    episodes: list[EpisodeBehaviour]

    @property
    def drone_episodes(self) -> list[DroneBehaviour]:
        return [d for e in self.episodes for d in e.drones]

    def counts(self, successful: bool = False) -> Counter:
        """Manoeuvre -> drone-episodes (only those that reached the goal with `successful`)."""
        return Counter(d.manoeuvre for d in self.drone_episodes if not successful or d.outcome == "goal")

    def majority(self) -> str | None:
        """The most common manoeuvre of the successful drone-episodes (None: no success)."""
        counts = self.counts(successful=True)
        return min(counts, key=lambda k: (-counts[k], k)) if counts else None

    def yield_priority(self) -> tuple[int, int]:
        """(episodes whose yields follow the priority rule, episodes with a yield)."""
        verdicts = [e.follows_priority for e in self.episodes if e.follows_priority is not None]
        return sum(verdicts), len(verdicts)

    def passing_order(self) -> tuple[int, int]:
        """(episodes going through the shared opening in priority order, episodes with an order)."""
        verdicts = [e.order_follows_priority for e in self.episodes if e.order_follows_priority is not None]
        return sum(verdicts), len(verdicts)

    def to_dict(self) -> dict:
        follows, with_yield = self.yield_priority()
        in_order, with_order = self.passing_order()
        return {
            "label": self.label, "episodes": len(self.episodes),
            "counts": dict(self.counts()), "success_counts": dict(self.counts(successful=True)),
            "outcomes": dict(Counter(d.outcome for d in self.drone_episodes)),
            "patterns": dict(Counter(e.pattern for e in self.episodes if e.success)),
            "majority": self.majority(),
            "yield_follows_priority": follows, "episodes_with_yield": with_yield,
            "order_follows_priority": in_order, "episodes_with_order": with_order,
        }


@dataclass
class BehaviourAnalysis:
    """Manoeuvres of one scenario across runs (seeds)."""

    scenario: str
    runs: list[RunBehaviour]

    @property
    def episodes(self) -> list[EpisodeBehaviour]:
        return [e for r in self.runs for e in r.episodes]

    def split(self) -> dict[str, float]:
        """Share of every manoeuvre among the successful drone-episodes of all runs."""
        return _shares(sum((r.counts(successful=True) for r in self.runs), Counter()))

    def pattern_split(self) -> dict[str, float]:
        """Share of every per-episode pattern among the successful episodes (multi-drone)."""
        return _shares(Counter(e.pattern for e in self.episodes if e.success))

    def dominant(self) -> str | None:
        """The manoeuvre holding `DOMINANT_SHARE` of the successes, or None (a split)."""
        split = self.split()
        top = next(iter(split), None)
        return top if top is not None and split[top] >= DOMINANT_SHARE else None

    def seed_majorities(self) -> dict[str, int]:
        """Manoeuvre -> runs in which it is the majority of the successes."""
        return dict(Counter(m for r in self.runs if (m := r.majority()) is not None).most_common())

    def yield_priority(self) -> tuple[int, int]:
        pairs = [r.yield_priority() for r in self.runs]
        return sum(p[0] for p in pairs), sum(p[1] for p in pairs)

    def passing_order(self) -> tuple[int, int]:
        pairs = [r.passing_order() for r in self.runs]
        return sum(p[0] for p in pairs), sum(p[1] for p in pairs)

    def by_outcome(self) -> dict[str, dict[str, int]]:
        """Manoeuvre -> outcome -> drone-episodes."""
        table: dict[str, Counter] = defaultdict(Counter)
        for episode in self.episodes:
            for d in episode.drones:
                table[d.manoeuvre][d.outcome] += 1
        return {k: dict(v) for k, v in sorted(table.items())}

    def statements(self) -> list[str]:
        """Plain-language findings: the split (or the dominant manoeuvre), seeds, yields."""
        split = self.split()
        successes = sum(r.counts(successful=True).total() for r in self.runs)
        if not split:
            return [f"{self.scenario}: no successful drone-episode in {len(self.episodes)} episodes"]
        dominant = self.dominant()
        head = f"mostly {dominant}" if dominant else "split"
        out = [f"{self.scenario}: {head}: {split_text(split)} of {successes} successful drone-episodes"]
        majorities = self.seed_majorities()
        out.append(f"majority per seed: {', '.join(f'{k} in {v}' for k, v in majorities.items())} "
                   f"of {len(self.runs)} seeds")
        patterns = self.pattern_split()
        if any("+" in p for p in patterns):
            out.append(f"per episode: {split_text(patterns)}")
        follows, with_yield = self.yield_priority()
        if with_yield:
            out.append(f"yield follows priority rule in {follows} of {with_yield} episodes")
        in_order, with_order = self.passing_order()
        if with_order:
            out.append(f"through the opening in priority order in {in_order} of {with_order} episodes")
        return out

    def to_dict(self) -> dict:
        follows, with_yield = self.yield_priority()
        return {
            "scenario": self.scenario, "seeds": len(self.runs), "episodes": len(self.episodes),
            "split": self.split(), "split_text": split_text(self.split()), "dominant": self.dominant(),
            "seed_majorities": self.seed_majorities(), "patterns": self.pattern_split(),
            "by_outcome": self.by_outcome(),
            "yield_priority": {"follows": follows, "episodes_with_yield": with_yield},
            "passing_order": dict(zip(("follows", "episodes_with_order"), self.passing_order(), strict=True)),
            "statements": self.statements(),
            "per_seed": [r.to_dict() for r in self.runs],
        }

    def report(self) -> str:
        lines = [f"behaviour ({len(self.runs)} seeds, {len(self.episodes)} episodes):"]
        lines += [f"  - {s}" for s in self.statements()]
        for run in self.runs:
            counts = run.counts()
            follows, with_yield = run.yield_priority()
            in_order, with_order = run.passing_order()
            extra = f"; yields by priority {follows}/{with_yield}" if with_yield else ""
            extra += f"; through the opening in priority order {in_order}/{with_order}" if with_order else ""
            lines.append(f"    seed {run.label}: " + ", ".join(f"{k} {v}" for k, v in counts.most_common())
                         + f" (success {sum(d.outcome == 'goal' for d in run.drone_episodes)}"
                         f"/{len(run.drone_episodes)}){extra}")
        return "\n".join(lines)
