"""Fly an episode again and keep what a picture of it needs (`rl/analysis/pictures.py`).

Two sources of actions:

* a logged training episode (`episodes.jsonl`: each drone's actions and the episode's reset seed):
  the `direct` backend is deterministic, so the same seed and actions in the run's own scenario
  fly the same episode again; `refly_logged` says where the re-flight differs from the log;
* the run's greedy policy (`greedy_pictures`): evaluation episode N of `sitl-bridge eval --seed S`.

Besides the drones' `Trace`s it records the episode's drawn layout and where every moving
obstacle was after reset and after each step (the env itself reports neither).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import pybullet as p

from sitl_bridge.envs.scenario import Scenario, load_scenario
from sitl_bridge.errors import ConfigError
from sitl_bridge.physics.simulation import Simulation
from sitl_bridge.rl.analysis.behaviour_summary import run_length
from sitl_bridge.rl.analysis.pictures import EpisodePicture
from sitl_bridge.rl.common.drones_env import DronesEnv, scenario_env_factory
from sitl_bridge.rl.common.episode_files import log_exists
from sitl_bridge.rl.common.episode_log import read_records
from sitl_bridge.rl.evaluation.rollout import Trace, eval_seeds, position_of, record_step
from sitl_bridge.rl.training.run_dir import EPISODES_FILE, read_run_files, run_dir_of, run_scenario

Chooser = Callable[[int, int, np.ndarray], "int | None"]
"""(drone, step, observation) -> action; None: no action left for this drone (stop flying)."""

POSITION_TOLERANCE_M = 0.05
"""A re-flown end position this close to the logged one counts as the same."""


def _mover_positions(sim: Simulation) -> dict[str, list[float]]:
    bodies = sim.obstacle_bodies
    return {o.name: [float(v) for v in p.getBasePositionAndOrientation(bodies[o.name],
                                                                        physicsClientId=sim.client_id)[0]]
            for o in sim.layout.obstacles if o.spec.mover is not None and o.name in bodies}


def fly(env: DronesEnv, scenario: Scenario, seed: int, choose: Chooser, *, episode: int = 0,
        title: str = "") -> EpisodePicture:
    """One episode from reset seed `seed`, every live drone acting with `choose`. A drone that
    `choose` has no action for ends the flight there (its trace's outcome: `unfinished`)."""
    backend = env.env.backend
    obs, infos = env.reset(seed)
    layout, movers_now = backend.with_simulation(lambda sim: (sim.layout, _mover_positions(sim)))
    movers = {name: [where] for name, where in movers_now.items()}
    traces = {i: Trace(episode, i, seed) for i in range(env.num_drones)}
    for i, trace in traces.items():
        info = infos.get(i, {})
        start = position_of(info)
        if start is not None:
            trace.positions_enu_m.append(start)
        goal = info.get("goal_enu_m")
        trace.goal_enu_m = None if goal is None else [float(v) for v in np.asarray(goal).reshape(-1)]
    while env.live:
        chosen = {i: choose(i, traces[i].steps, obs[i]) for i in env.live}
        if any(a is None for a in chosen.values()):
            for i in env.live:
                traces[i].outcome = "unfinished"
            break
        acting = {i: a if isinstance(a, (list, np.ndarray)) else int(a)  # type: ignore[arg-type]
                  for i, a in chosen.items()}
        result = env.step(acting)
        record_step(traces, acting, result)
        obs.update(result.obs)
        for name, where in backend.with_simulation(_mover_positions).items():
            movers.setdefault(name, []).append(where)
    return EpisodePicture(scenario, layout, list(traces.values()), movers, title)


def logged_episode(run_dir: str | Path, episode: int) -> list[dict]:
    """The episode log's records of `episode` (one per drone, by drone); ValueError naming the
    episodes the log holds when it has no such episode."""
    folder = run_dir_of(run_dir)
    if folder is None:
        raise ConfigError(f"{run_dir}: not a run directory (no run.json)")
    log = folder / EPISODES_FILE
    records = read_records(log) if log_exists(log) else []
    if not records:
        raise ValueError(f"{log}: holds no logged episodes")
    mine = {r["drone"]: r for r in records if r["episode"] == episode}  # the last record of a drone wins
    if not mine:
        numbers = sorted({int(r["episode"]) for r in records})
        raise ValueError(f"{folder}: no episode {episode} in {EPISODES_FILE} "
                         f"(it holds episodes {numbers[0]}..{numbers[-1]})")
    return [mine[d] for d in sorted(mine)]


def compare(records: Sequence[dict], traces: Sequence[Trace]) -> list[str]:
    """Where re-flown traces differ from the logged records: outcome, steps, reward, end position."""
    by_drone = {t.drone: t for t in traces}
    differences: list[str] = []
    for record in records:
        drone = int(record["drone"])
        trace = by_drone.get(drone)
        if trace is None:
            differences.append(f"drone {drone}: not flown")
            continue
        said = []
        if trace.outcome != record["outcome"]:
            said.append(f"outcome {trace.outcome} (logged {record['outcome']})")
        if trace.steps != len(record["actions"]):
            said.append(f"{trace.steps} steps (logged {len(record['actions'])})")
        if abs(trace.reward - float(record["reward"])) > 1e-3 * max(1.0, abs(float(record["reward"]))):
            said.append(f"reward {trace.reward:.2f} (logged {float(record['reward']):.2f})")
        logged_end = (record.get("extra") or {}).get("position_enu_m")
        if logged_end is not None and trace.positions_enu_m:
            gap = float(np.linalg.norm(np.asarray(trace.positions_enu_m[-1]) - np.asarray(logged_end, float)))
            if gap > POSITION_TOLERANCE_M:
                said.append(f"ends {gap:.2f} m from the logged end position")
        if said:
            differences.append(f"drone {drone}: " + ", ".join(said))
    return differences


def refly_logged(run_dir: str | Path, episode: int, *, autopilot: str = "direct") -> tuple[EpisodePicture, list[str]]:
    """Logged training episode `episode` of a run flown again (same reset seed, same actions, the
    run's own scenario); with the differences from the log ([] when it is the same episode)."""
    records = logged_episode(run_dir, episode)
    seed = int(records[0].get("env_seed", 0))
    actions = {int(r["drone"]): [a if isinstance(a, list) else int(a) for a in r["actions"]] for r in records}
    world = run_scenario(run_dir)
    scenario = load_scenario(world)

    def choose(drone: int, step: int, _obs: np.ndarray) -> int | None:
        mine = actions.get(drone, [])
        return mine[step] if step < len(mine) else None

    env = DronesEnv(scenario_env_factory(world, autopilot)(seed))
    try:
        picture = fly(env, scenario, seed, choose, episode=episode)
    finally:
        env.close()
    differences = compare(records, picture.traces)
    trained_with = read_run_files(run_dir_of(run_dir) or run_dir)[0].autopilot
    if differences and trained_with != autopilot:
        differences.append(f"the run trained with the {trained_with} backend, re-flown with {autopilot}")
    picture.title = (f"{scenario.name}: training episode {episode} (reset seed {seed}, "
                     f"epsilon {float(records[0].get('epsilon', 0.0)):.2f})"
                     + ("; re-flown, differs from the log" if differences else ""))
    return picture, differences


def greedy_pictures(checkpoint: str | Path, episodes: Sequence[int], *, seed: int = 0,
                    world: str | Path | None = None, autopilot: str = "direct") -> list[EpisodePicture]:
    """The greedy policy of a checkpoint (file or run directory: its newest valid checkpoint) in
    evaluation episodes `episodes` of `sitl-bridge eval --seed seed` (same reset seeds), in the
    run's own scenario unless `world` names another."""
    from sitl_bridge.rl.learner.policy import policy_from_checkpoint

    if any(n < 0 for n in episodes):
        raise ValueError(f"episode numbers start at 0, got {min(episodes)}")
    policy = policy_from_checkpoint(checkpoint)
    world = world or run_scenario(checkpoint)
    scenario = load_scenario(world)
    seeds = eval_seeds(seed, max(episodes, default=-1) + 1)
    env = DronesEnv(scenario_env_factory(world, autopilot)(seed))
    try:
        return [fly(env, scenario, seeds[n], lambda _d, _s, obs: policy(obs), episode=n,
                    title=f"{scenario.name}: greedy episode {n} (reset seed {seeds[n]}, "
                          f"{policy.source.name}, {policy.episode} training episodes)")
                for n in episodes]
    finally:
        env.close()


def typical(pictures: Sequence[EpisodePicture], count: int) -> list[tuple[EpisodePicture, str]]:
    """Up to `count` pictures, one per behaviour, most common first (a behaviour: every drone's
    outcome and run-length action sequence), each with a title saying how common it is."""
    groups: dict[tuple, list[EpisodePicture]] = {}
    for picture in pictures:
        key = tuple((t.outcome, run_length(t.actions)) for t in picture.traces)
        groups.setdefault(key, []).append(picture)
    ranked = sorted(groups.values(), key=len, reverse=True)[:count]
    total = len(pictures)
    chosen = []
    for members in ranked:
        first = members[0]
        outcomes = Counter(t.outcome for t in first.traces)
        said = ", ".join(f"{k}" if n == 1 else f"{n} x {k}" for k, n in outcomes.items())
        chosen.append((first, f"{len(members)} of {total} episodes: {said} (episode {first.traces[0].episode})"))
    return chosen
