"""Per-encounter-type evaluation: N episodes of every type of an encounter world, per policy.

Every policy flies the same episodes: the reset seeds `eval_seeds(seed, ...)` in order, each
episode's type read at its reset (`info["encounter"]`, `rollout.encounter_label`), an episode
flown only while its type has fewer than N, so which seeds fly depends on the world alone, never
on the policy. Per episode one `EncounterEpisode` record; per policy and type the table counts
episodes (the independent trials: the drones of one episode are not independent of each other):

- success: every drone of the episode reached its goal;
- collision: any drone of it crashed (into a drone, the wall, the ground);
- loss of separation: two of its drones closer than `separation.SEPARATION_M` (1 m) at a
  recorded step (`separation.episode_least_distance`);

each with its Wilson 95 % interval, and over the drones that reached their goal the mean time to
goal (decisions x the action's duration, simulated s: a late entrant's held time counts, it is
part of its trip) and the mean path length (m, along the recorded positions), each with its 95 %
t interval.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from sitl_bridge.rl.common.drones_env import DronesEnv
from sitl_bridge.rl.common.progress import Progress
from sitl_bridge.rl.common.stats import mean_ci95, wilson_interval
from sitl_bridge.rl.evaluation.rollout import Trace, encounter_label, eval_seeds, fly_episode
from sitl_bridge.rl.evaluation.separation import SEPARATION_M, episode_least_distance
from sitl_bridge.world.schema import World

MAX_EPISODES_PER_TYPE = 50
"""Seeds looked at per wanted episode before giving up on a rare type (its weight tiny)."""


def encounter_labels(world: World) -> list[str]:
    """The type labels episodes of `world` can report (`rollout.encounter_label`), in file order."""
    if world.encounter is None:
        raise ValueError(f"{world.source}: no world.encounter: a per-type evaluation needs an encounter family")
    labels: list[str] = []
    for kind in world.encounter.types:
        late = kind.start_delay_s[1] > 0.0 and kind.kind != "overtaking"
        label = f"{kind.kind}, late entry" if late else kind.kind
        if label not in labels:
            labels.append(label)
        if late and kind.start_delay_s[0] <= 0.0 and kind.kind not in labels:
            labels.append(kind.kind)  # a delay range from 0 can draw no delay at all
    return labels


def path_length_m(positions: Sequence[Sequence[float]]) -> float:
    """Length of the polyline through `positions` (m)."""
    points = np.asarray(positions, dtype=float).reshape(-1, 3)
    return float(np.sum(np.linalg.norm(np.diff(points, axis=0), axis=1))) if len(points) > 1 else 0.0


@dataclass(frozen=True)
class EncounterEpisode:
    """One episode of one policy, as the per-type table counts it."""

    policy: str
    world: str
    encounter: str
    episode: int
    """Index of its seed in `eval_seeds(seed, ...)`."""
    seed: int
    drones: int
    reached: int
    """Drones that reached their goal."""
    crashed: int
    least_distance_m: float | None
    times_to_goal_s: tuple[float, ...]
    """Per drone that reached its goal."""
    path_lengths_m: tuple[float, ...]
    """Per drone that reached its goal."""

    @property
    def success(self) -> bool:
        return self.reached == self.drones

    @property
    def collision(self) -> bool:
        return self.crashed > 0

    @property
    def lost_separation(self) -> bool:
        return self.least_distance_m is not None and self.least_distance_m < SEPARATION_M

    def to_dict(self) -> dict:
        return {**asdict(self), "success": self.success, "collision": self.collision,
                "lost_separation": self.lost_separation}


def episode_record(policy: str, world: str, traces: Sequence[Trace], action_duration_s: float) -> EncounterEpisode:
    """The record of one episode's traces (every drone's)."""
    first = traces[0]
    if first.encounter is None:
        raise ValueError(f"{world}: episode {first.episode} reported no encounter type (not an encounter world)")
    arrived = [t for t in traces if t.outcome == "goal"]
    return EncounterEpisode(
        policy=policy, world=world, encounter=first.encounter, episode=first.episode, seed=first.seed,
        drones=len(traces), reached=len(arrived), crashed=sum(t.outcome == "crash" for t in traces),
        least_distance_m=episode_least_distance(traces),
        times_to_goal_s=tuple(t.steps * action_duration_s for t in arrived),
        path_lengths_m=tuple(path_length_m(t.positions_enu_m) for t in arrived))


def fly_per_type(env: DronesEnv, policy: Callable[[np.ndarray], int], *, policy_name: str, world: str,
                 labels: Sequence[str], per_type: int, seed: int, action_duration_s: float,
                 progress: bool = False) -> list[EncounterEpisode]:
    """`per_type` episodes of every type in `labels` (module docstring: the same seeds for every
    policy); fewer of a type only when `MAX_EPISODES_PER_TYPE` x per_type x types seeds did not hold
    them (the table shows each type's count)."""
    wanted = {label: per_type for label in labels}
    flown: Counter[str] = Counter()
    records: list[EncounterEpisode] = []
    seeds = eval_seeds(seed, MAX_EPISODES_PER_TYPE * per_type * max(1, len(labels)))
    with Progress(per_type * len(labels), f"{policy_name} per encounter type", enabled=progress) as bar:
        for episode, reset_seed in enumerate(seeds):
            if all(flown[label] >= n for label, n in wanted.items()):
                break
            obs, infos = env.reset(reset_seed)
            label = encounter_label(infos.get(0, {}))
            if label is None:
                raise ValueError(f"{world}: its episodes report no encounter type (not an encounter world)")
            if label not in wanted:
                raise ValueError(f"{world}: an episode of type {label!r}, not one of {', '.join(labels)}")
            if flown[label] >= wanted[label]:
                continue  # this type is complete: the next seed (a reset is all it cost)
            traces = fly_episode(env, policy, episode, reset_seed, obs, infos)
            records.append(episode_record(policy_name, world, traces, action_duration_s))
            flown[label] += 1
            bar.update(1)
    return records


@dataclass(frozen=True)
class Rate:
    """A share of episodes with its Wilson 95 % interval."""

    count: int
    of: int
    low: float
    high: float

    @property
    def value(self) -> float:
        return self.count / self.of if self.of else 0.0

    @classmethod
    def of_flags(cls, flags: Sequence[bool]) -> Rate:
        count = int(sum(flags))
        low, high = wilson_interval(count, len(flags))
        return cls(count, len(flags), low, high)

    def to_dict(self) -> dict:
        return {"rate": self.value, "count": self.count, "of": self.of, "ci95": [self.low, self.high]}

    def cell(self) -> str:
        return f"{self.value:.0%} [{self.low:.0%}, {self.high:.0%}]"


@dataclass(frozen=True)
class Mean:
    """A mean with its 95 % t interval (None: fewer than two values)."""

    value: float | None
    n: int
    interval: tuple[float, float] | None

    @classmethod
    def of_values(cls, values: Sequence[float]) -> Mean:
        if not values:
            return cls(None, 0, None)
        mean, interval = mean_ci95(list(values))
        return cls(float(mean), len(values), interval)

    def to_dict(self) -> dict:
        return {"mean": self.value, "n": self.n, "ci95": None if self.interval is None else list(self.interval)}

    def cell(self, decimals: int = 1) -> str:
        if self.value is None:
            return "-"
        if self.interval is None:
            return f"{self.value:.{decimals}f}"
        return f"{self.value:.{decimals}f} ± {(self.interval[1] - self.interval[0]) / 2:.{decimals}f}"


@dataclass(frozen=True)
class TypeRow:
    """One policy on one encounter type."""

    policy: str
    world: str
    encounter: str
    episodes: int
    success: Rate
    collision: Rate
    lost_separation: Rate
    time_to_goal_s: Mean
    path_length_m: Mean

    def to_dict(self) -> dict:
        return {"policy": self.policy, "world": self.world, "encounter": self.encounter, "episodes": self.episodes,
                "success": self.success.to_dict(), "collision": self.collision.to_dict(),
                "lost_separation": self.lost_separation.to_dict(), "time_to_goal_s": self.time_to_goal_s.to_dict(),
                "path_length_m": self.path_length_m.to_dict()}


def by_type(records: Sequence[EncounterEpisode]) -> list[TypeRow]:
    """One row per (world, encounter type, policy), in the order they first appear."""
    groups: dict[tuple[str, str, str], list[EncounterEpisode]] = {}
    for record in records:
        groups.setdefault((record.world, record.encounter, record.policy), []).append(record)
    return [TypeRow(policy, world, encounter, len(group),
                    Rate.of_flags([r.success for r in group]), Rate.of_flags([r.collision for r in group]),
                    Rate.of_flags([r.lost_separation for r in group]),
                    Mean.of_values([t for r in group for t in r.times_to_goal_s]),
                    Mean.of_values([d for r in group for d in r.path_lengths_m]))
            for (world, encounter, policy), group in sorted(groups.items(), key=lambda item: item[0][:2])]


def markdown_table(rows: Sequence[TypeRow]) -> str:
    """The rows as a markdown table (rates: share [Wilson 95 %]; means: value ± half the 95 % t interval)."""
    lines = ["| world | encounter type | policy | episodes | success | collision | loss of separation (< 1 m) "
             "| time to goal (s) | path length (m) |", "|---|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r.world} | {r.encounter} | {r.policy} | {r.episodes} | {r.success.cell()} | {r.collision.cell()} "
              f"| {r.lost_separation.cell()} | {r.time_to_goal_s.cell()} | {r.path_length_m.cell()} |" for r in rows]
    return "\n".join(lines)
