"""The warning for runs that learn to end episodes early (rl/training/early_end.py): synthetic episode
streams, and the committed `two_blocks` runs, where it must name the failed seeds only."""

from __future__ import annotations

import json
from collections import deque
from pathlib import Path

import pytest
import yaml

from sitl_bridge.envs.scenario import load_scenario
from sitl_bridge.rl.common.episode_files import log_exists
from sitl_bridge.rl.common.episode_log import EpisodeRecord, read_records
from sitl_bridge.rl.training.early_end import EarlyEndWatch, flying_on_value
from sitl_bridge.rl.training.run_dir import run_scenario

ROOT = Path(__file__).resolve().parents[1]
TWO_BLOCKS_RUNS = ROOT / "docs/results/generalization/runs/scenarios/two_blocks"
THESIS_REWARDS = {"per_step": -5.0, "crash": -100.0, "goal_reached": 500.0}


def record(outcome: str, steps: int, episode: int = 0) -> EpisodeRecord:
    return EpisodeRecord(episode=episode, drone=0, actions=[3] * steps, reward=0.0, reward_terms={},
                         outcome=outcome, steps=steps, sim_time_s=float(steps), wall_time_s=0.0, epsilon=0.5,
                         mean_loss=None)


def feed(watch: EarlyEndWatch, records: list[EpisodeRecord]) -> list[str]:
    return [message for r in records if (message := watch.add([r]))]


def test_flying_on_is_worth_per_step_over_one_minus_gamma() -> None:
    assert flying_on_value(-5.0, 0.99) == pytest.approx(-500.0)
    assert flying_on_value(-5.0, 1.0) is None


def test_a_window_of_early_crashes_without_a_goal_warns_once_and_says_why() -> None:
    watch = EarlyEndWatch(max_steps=45, rewards=THESIS_REWARDS, gamma=0.99, window=50)
    messages = feed(watch, [record("crash" if k % 3 else "out", 3) for k in range(120)])
    assert len(messages) == 1  # once, at the 50th
    assert "no goal in the last 50 drone-episodes, and 100% of them" in messages[0]
    assert "within 11 steps" in messages[0]  # a quarter of 45
    assert "= -500" in messages[0] and "a crash -100" in messages[0]


def test_the_warning_names_goal_seeking_exploration_its_default_and_its_cost() -> None:
    (message,) = feed(EarlyEndWatch(max_steps=45, rewards=THESIS_REWARDS, gamma=0.99, window=10),
                      [record("crash", 2)] * 10)
    assert "train: guided_explore_episodes: 100" in message
    assert "off by default" in message and "knows the static obstacles" in message


def test_a_run_that_had_goal_seeking_exploration_is_told_to_give_it_more() -> None:
    watch = EarlyEndWatch(max_steps=45, rewards=THESIS_REWARDS, gamma=0.99, window=10, guided_episodes=100)
    (message,) = feed(watch, [record("crash", 2)] * 10)
    assert "was on for the first 100 episodes" in message and "larger guided_explore_episodes" in message
    assert "off by default" not in message


def test_an_algorithm_without_goal_seeking_exploration_is_not_told_to_use_it() -> None:
    watch = EarlyEndWatch(max_steps=45, rewards=THESIS_REWARDS, gamma=0.99, window=10, guided_episodes=None)
    (message,) = feed(watch, [record("crash", 2)] * 10)
    assert "guided_explore" not in message and "explore_repeat_max" in message


@pytest.mark.parametrize("stream", [
    [record("crash", 3)] * 49 + [record("goal", 20)],           # a goal in the window
    [record("crash", 3)] * 40 + [record("timeout", 45)] * 10,   # 80 % early ends only
    [record("crash", 20)] * 50,                                 # crashes, but late in the episode
    [record("crash", 3)] * 49,                                  # the window is not full yet
])
def test_no_warning_where_the_pattern_does_not_hold(stream: list[EpisodeRecord]) -> None:
    assert feed(EarlyEndWatch(max_steps=45, rewards=THESIS_REWARDS, gamma=0.99, window=50), stream) == []


def test_a_crash_dearer_than_flying_on_is_not_given_as_the_reason() -> None:
    watch = EarlyEndWatch(max_steps=45, rewards={**THESIS_REWARDS, "crash": -600.0}, gamma=0.99, window=10)
    (message,) = feed(watch, [record("crash", 2)] * 10)
    assert "per_step / (1 - gamma)" not in message


def test_on_the_committed_two_blocks_runs_it_names_exactly_the_seeds_that_never_solved_it() -> None:
    """Replays each finished run's episode log through the watch (the trainer feeds it the same
    records): a warning only where the run never reached 90 % greedy success."""
    jobs = sorted(TWO_BLOCKS_RUNS.glob("seed*/done.json"))
    if len(jobs) < 7:
        pytest.skip("the committed two_blocks runs are not here")
    warned, failed = set(), set()
    for done in jobs:
        (run,) = [d for d in done.parent.iterdir() if log_exists(d / "episodes.jsonl")]
        gamma = yaml.safe_load((run / "config.yaml").read_text())["gamma"]
        watch = EarlyEndWatch.of(load_scenario(run_scenario(run)), gamma)
        seed = int(done.parent.name[4:])
        fields = EpisodeRecord.__dataclass_fields__
        for row in read_records(run / "episodes.jsonl"):
            if watch.add([EpisodeRecord(**{k: v for k, v in row.items() if k in fields})]):
                warned.add(seed)
                break
        evals = [json.loads(line) for line in (run / "evals.jsonl").read_text().splitlines() if line.strip()]
        if max(e["success_rate"] for e in evals) < 0.9:
            failed.add(seed)
    assert failed and warned == failed


@pytest.mark.parametrize("guided", [0, 4])
def test_the_trainer_feeds_its_episodes_to_the_watch_and_warns(tmp_path: Path, guided: int) -> None:
    """The wiring: a trainer on a real scenario builds the watch from it and from its
    `guided_explore_episodes`, and the records it persists reach the watch; the warning goes to
    the trainer's `warn`."""
    from test_rl_helpers import tiny_config

    from sitl_bridge.rl.common.drones_env import scenario_env_factory
    from sitl_bridge.rl.training.run_dir import RunSpec
    from sitl_bridge.rl.training.trainer import Trainer

    world = str(ROOT / "worlds/empty.yaml")
    warnings: list[str] = []
    with Trainer.start(tmp_path, RunSpec(world=world), tiny_config(guided_explore_episodes=guided),
                       scenario_env_factory(world), progress=False, warn=warnings.append) as trainer:
        assert trainer.early_end is not None
        assert trainer.early_end.early_steps == load_scenario(world).task.max_steps // 4
        assert trainer.early_end.guided_episodes == guided
        trainer.early_end.recent = deque(maxlen=3)
        trainer.persist([record("crash", 1, episode=k) for k in range(3)], [])
    assert len(warnings) == 1
    assert "learning to end its episodes early" in warnings[0]
    assert ("was on for the first 4 episodes" in warnings[0]) == bool(guided)
