"""Greedy evaluation of a trained policy: success rate, crash rate, mean reward, mean steps."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sitl_bridge.rl.common.drones_env import DronesEnv, EnvFactory, scenario_env_factory
from sitl_bridge.rl.common.progress import Progress
from sitl_bridge.rl.evaluation.rollout import Trace, eval_seeds, rollout
from sitl_bridge.rl.learner.policy import policy_from_checkpoint


@dataclass
class EvalResult:
    """Greedy performance over `episodes` episodes (rates count every drone-episode)."""

    world: str
    episodes: int
    drone_episodes: int
    success_rate: float
    crash_rate: float
    out_rate: float
    timeout_rate: float
    mean_reward: float
    mean_steps: float
    mean_steps_success: float | None
    """Mean steps of the successful episodes (None if none succeeded)."""

    def to_dict(self) -> dict:
        return asdict(self)

    def summary(self) -> str:
        return (f"{self.world}: success {self.success_rate:.0%}, crash {self.crash_rate:.0%}, "
                f"out {self.out_rate:.0%}, timeout {self.timeout_rate:.0%}, mean reward "
                f"{self.mean_reward:.1f}, mean steps {self.mean_steps:.1f} ({self.episodes} episodes)")


def summarize(world: str, episodes: int, traces: list[Trace]) -> EvalResult:
    """Rates and means of a list of rollouts."""
    def rate(outcome: str) -> float:
        return float(np.mean([t.outcome == outcome for t in traces])) if traces else 0.0

    wins = [t.steps for t in traces if t.outcome == "goal"]
    return EvalResult(
        world=world, episodes=episodes, drone_episodes=len(traces),
        success_rate=rate("goal"), crash_rate=rate("crash"), out_rate=rate("out"), timeout_rate=rate("timeout"),
        mean_reward=float(np.mean([t.reward for t in traces])) if traces else 0.0,
        mean_steps=float(np.mean([t.steps for t in traces])) if traces else 0.0,
        mean_steps_success=float(np.mean(wins)) if wins else None,
    )


def evaluate_policy(policy: Callable[[np.ndarray], int], env_factory: EnvFactory, *, world: str,
                    episodes: int, seed: int = 0, progress: bool = False,
                    videos: Any = None) -> tuple[EvalResult, list[Trace]]:
    """Fly `policy` greedily for `episodes` episodes on fresh seeds, in a new env."""
    env = DronesEnv(env_factory(seed))
    try:
        return evaluate_on(env, policy, world=world, episodes=episodes, seed=seed, progress=progress,
                           videos=videos)
    finally:
        env.close()


def evaluate_on(env: DronesEnv, policy: Callable[[np.ndarray], int], *, world: str, episodes: int,
                seed: int = 0, progress: bool = False, desc: str = "evaluation",
                videos: Any = None, flown: Sequence[Trace] = (),
                beat: Callable[[str], None] | None = None) -> tuple[EvalResult, list[Trace]]:
    """Fly `policy` greedily for `episodes` episodes on evaluation seeds in an open env
    (with `progress`, a bar or periodic lines on stderr; with `videos`, recorded; `beat`
    is called after each episode with e.g. "evaluation 3/100": a training run's heartbeat).

    `flown`: the traces of a shorter evaluation of the same policy on the same seeds, which this
    one extends: only the episodes after them are flown (greedy flights are deterministic, so
    flying those seeds again would repeat them), and the result counts all of them."""
    done = len({t.episode for t in flown})
    goals = [t.outcome == "goal" for t in flown]  # drone-episodes so far, as the result counts them
    with Progress(episodes - done, desc, enabled=progress) as bar:
        def count(traces: list[Trace]) -> None:
            goals.extend(t.outcome == "goal" for t in traces)
            bar.update(1, success=f"{np.mean(goals):.0%}")
            if beat is not None:
                beat(f"{desc} {done + traces[0].episode + 1}/{episodes}")

        traces = rollout(env, policy, eval_seeds(seed, episodes)[done:], on_episode=count, videos=videos)
    for trace in traces:  # numbered within the whole evaluation
        trace.episode += done
    traces = [*flown, *traces]
    return summarize(world, episodes, traces), traces


@dataclass(frozen=True)
class ConstantBaseline:
    """The best policy that always picks one action: what a learned policy must beat."""

    action: int | list[float]
    """A discrete code, or a continuous command (`constant_actions`)."""
    success_rate: float
    per_action: list[float]
    """Greedy success of each constant action, in `constant_actions`' order."""

    def to_dict(self) -> dict:
        return asdict(self)


def constant_actions(env: DronesEnv) -> list[int | list[float]]:
    """The constant policies a learned one must beat: every discrete code, or for a continuous
    (Box) action full speed along each of its first three axes both ways, and zero (hover)."""
    if not env.continuous:
        return list(range(env.n_actions))
    size = int(np.prod(env.action_space.shape))
    axes = [[float(sign) if k == axis else 0.0 for k in range(size)]
            for axis in range(min(size, 3)) for sign in (1, -1)]
    return [*axes, [0.0] * size]


def constant_action_baseline(env: DronesEnv, *, world: str, episodes: int, seed: int = 0,
                             progress: bool = False,
                             beat: Callable[[str], None] | None = None) -> ConstantBaseline:
    """Success of every constant-action policy (`constant_actions`) on the evaluation episodes
    of `evaluate_on` (same seeds), and the best of them (`beat` as in `evaluate_on`). A scenario
    that a constant action solves needs no learning."""
    rates = []
    actions = constant_actions(env)
    for action in actions:
        flown = np.asarray(action, dtype=np.float32) if env.continuous else action
        result, _ = evaluate_on(env, lambda _obs, a=flown: a, world=world, episodes=episodes, seed=seed,
                                progress=progress, desc=f"constant action {action}", beat=beat)
        rates.append(result.success_rate)
    best = int(np.argmax(rates))
    return ConstantBaseline(actions[best], rates[best], rates)


def evaluate_checkpoint(checkpoint: str | Path, world: str | Path, *, episodes: int, autopilot: str = "direct",
                        seed: int = 0, progress: bool = False,
                        video_dir: str | Path | None = None) -> tuple[EvalResult, list[Trace]]:
    """Greedy evaluation of a checkpoint (file or run directory) in the scenario `world`
    (with `video_dir`: one MP4 per episode there)."""
    return evaluate_in_world(policy_from_checkpoint(checkpoint), world, episodes=episodes, autopilot=autopilot,
                             seed=seed, progress=progress, video_dir=video_dir)


def evaluate_in_world(policy: Callable[[np.ndarray], int], world: str | Path, *, episodes: int,
                      autopilot: str = "direct", seed: int = 0, progress: bool = False,
                      video_dir: str | Path | None = None) -> tuple[EvalResult, list[Trace]]:
    """Fly any policy (a network's greedy one, a scripted rule set) greedily in the scenario
    file `world` on the evaluation seeds: the one path behind every success rate we report."""
    if video_dir is None:
        return evaluate_policy(policy, scenario_env_factory(world, autopilot), world=str(world),
                               episodes=episodes, seed=seed, progress=progress)
    from sitl_bridge.envs.scenario import load_scenario
    from sitl_bridge.rl.evaluation.video import EpisodeVideos

    videos = EpisodeVideos.into_folder(video_dir, load_scenario(world).task.render.fps)
    return evaluate_policy(policy, scenario_env_factory(world, autopilot, render_mode="rgb_array_list"),
                           world=str(world), episodes=episodes, seed=seed, progress=progress, videos=videos)
