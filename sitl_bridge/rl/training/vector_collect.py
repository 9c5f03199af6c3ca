"""DQN experience from N copies of a scenario flown at once (`train.num_envs` > 1).

The copies are `sitl_bridge.make_vec_env`'s (for a scenario file; any other env factory gives N
envs of its own), each seen through `DronesEnv`. Episodes run in waves of N: the wave that
starts at episode e resets copy k with `episode_seed(seed, e + k)`; each vector step picks the
actions of every copy still flying with one network call (`DQNAgent.act_batch`), steps those
copies, adds their transitions to the replay in copy order and makes the DQN updates due for
them (`train_every` counts env transitions; epsilon follows the global step, the learning
rate is the wave's first episode's). When the wave's last episode ends, its replay rows
and then its records, in episode order, are persisted, and the trainer writes one checkpoint.

Why waves, not a rolling start (a finished copy starting the next episode at once): a
checkpoint must describe a state with no episode in flight, or a resumed run could not repeat
what follows it (an env's mid-episode state is not saved), and the replay rows on disk must be
in the order they entered the replay. With waves a resumed run is exact and a killed one loses
at most the wave in flight.

Why the copies are stepped one by one rather than with `VectorEnv.step`: that steps every copy,
so a copy whose episode is over would be auto-reset (an unseeded reset of about six steps' cost
on `direct`) and flown on for nothing until the wave ends. Stepping the simulator dominates the
cost of a training step, so a wave costs the same env work as its episodes one at a time; what
it saves is the per-step network call and its Python overhead.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from sitl_bridge.errors import ConfigError
from sitl_bridge.rl.common.drones_env import DronesEnv, EnvFactory
from sitl_bridge.rl.common.episode_log import EpisodeRecord
from sitl_bridge.rl.evaluation.rollout import episode_seed
from sitl_bridge.rl.learner.dqn_learner import DQNLearner
from sitl_bridge.rl.learner.nstep import NStepFolder
from sitl_bridge.rl.training.episode_tally import EpisodeTally


@dataclass
class _Flight:
    """One copy's episode of a wave."""

    env: DronesEnv
    episode: int
    env_seed: int
    obs: dict[int, np.ndarray]
    tally: EpisodeTally
    folder: NStepFolder | None
    end: tuple[int, int, float] | None = None
    """(global step, losses so far, wall seconds since the wave began) when its episode ended."""


class VectorCollector:
    """N copies of the training scenario and the wave loop that flies them."""

    def __init__(self, env_factory: EnvFactory, seed: int, num_envs: int) -> None:
        vector = getattr(env_factory, "vector", None)  # a scenario's factory: make_vec_env
        self._vec = vector(seed, num_envs) if vector is not None else None
        envs = list(self._vec.envs) if self._vec is not None else [env_factory(seed + k) for k in range(num_envs)]
        self.copies = [DronesEnv(env) for env in envs]
        if self.copies[0].num_drones > 1:
            self.close()
            raise ConfigError(f"num_envs {num_envs}: several copies at once need a single-drone scenario")

    def close(self) -> None:
        """Close every copy."""
        if self._vec is not None:
            self._vec.close()
        else:
            for copy in self.copies:
                copy.close()

    def run_wave(self, learner: DQNLearner, run_seed: int,
                 persist: Callable[[list[EpisodeRecord], list[np.ndarray]], None]) -> list[EpisodeRecord]:
        """Fly the next wave of episodes (fewer than N when the budget ends sooner) with
        `learner`'s actions, let it learn from them, then `persist(records, new replay rows)`;
        the records come in episode order."""
        first = learner.episode
        count = max(1, min(len(self.copies), learner.config.episodes - first))
        learner.start_episodes()
        wall_start, cpu_start = time.perf_counter(), time.process_time()
        epsilon_start = learner.epsilon()
        flights = []
        for k, copy in enumerate(self.copies[:count]):
            env_seed = episode_seed(run_seed, first + k)
            obs, reset_infos = copy.reset(env_seed)
            flights.append(_Flight(copy, first + k, env_seed, obs, EpisodeTally(copy.num_drones, reset_infos),
                                   learner.n_step_folder()))
        learner.observe(np.stack([o for f in flights for o in f.obs.values()]))
        losses: list[float] = []
        new_rows: list[np.ndarray] = []
        while flying := [f for f in flights if f.env.live]:
            self._step(learner, flying, new_rows)
            learner.after_steps(len(flying), losses)
            for f in flying:
                if not f.env.live:
                    f.end = (learner.global_step, len(losses), time.perf_counter() - wall_start)
        learner.end_episodes(count)

        records = []
        cpu_share = (time.process_time() - cpu_start) / count  # the wave's CPU, summed over its episodes
        for f in flights:
            assert f.end is not None
            global_step, n_losses, wall = f.end
            records += f.tally.records(
                episode=f.episode, wall_time_s=wall, epsilon=epsilon_start, global_step=global_step,
                mean_loss=float(np.mean(losses[:n_losses])) if n_losses else None, env_seed=f.env_seed,
                cpu_time_s=cpu_share)
        persist(records, new_rows)
        return records

    @staticmethod
    def _step(learner: DQNLearner, flying: list[_Flight], new_rows: list[np.ndarray]) -> None:
        """One env step of every flight in `flying`, actions from one network call."""
        batch = np.stack([f.obs[i] for f in flying for i in f.env.live])
        actions = iter(learner.act_batch(batch, learner.epsilon()))
        seen: list[np.ndarray] = []
        for f in flying:
            chosen = {i: int(next(actions)) for i in f.env.live}  # the batch's order
            result = f.env.step(chosen)
            for i, action in chosen.items():
                f.tally.add(i, action, result.rewards[i], result.terminated[i], result.truncated[i],
                            result.infos.get(i, {}))
            rows = learner.transition_rows(f.folder, chosen, f.obs, result)
            if len(rows):
                learner.remember(rows)
                new_rows.append(rows)
            seen += [result.obs[i] for i in chosen]
            f.obs.update(result.obs)
        learner.observe(np.stack(seen))
