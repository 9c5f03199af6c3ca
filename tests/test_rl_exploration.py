"""ez-greedy (rl/learner/exploration.py): the run-length distribution, runs that repeat one action without
greedy decisions, plain epsilon-greedy's random stream when no run is going on, and the option's
wiring into the trainer and its config."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
from test_rl_helpers import corridor_factory, tiny_config

from sitl_bridge.errors import ConfigError
from sitl_bridge.rl.learner.exploration import RepeatedExploration, repeat_probabilities
from sitl_bridge.rl.training.run_dir import RunSpec
from sitl_bridge.rl.training.trainer import Trainer

GREEDY = 9
"""What the stand-in network always chooses (outside the random actions 0..7)."""


def explorer(max_repeat: int = 8, exponent: float = 2.0) -> RepeatedExploration:
    return RepeatedExploration(lambda obs: GREEDY, n_actions=8, max_repeat=max_repeat, exponent=exponent)


def test_run_lengths_follow_the_truncated_zeta_distribution() -> None:
    p = repeat_probabilities(4, 2.0)
    expected = np.array([1, 1 / 4, 1 / 9, 1 / 16]) / (1 + 1 / 4 + 1 / 9 + 1 / 16)
    assert p == pytest.approx(expected)
    # always exploring: every step with nothing left of a run starts one; count their lengths
    ez, rng = explorer(max_repeat=4), np.random.default_rng(0)
    lengths: Counter[int] = Counter()
    for _ in range(40_000):
        starts = ez.runs.get(0, (0, 0))[1] == 0
        ez.act(0, np.zeros(1), 1.0, rng)
        if starts:
            lengths[ez.runs[0][1] + 1] += 1
    total = sum(lengths.values())
    assert [lengths[n] / total for n in (1, 2, 3, 4)] == pytest.approx(expected, abs=0.01)


def test_a_run_repeats_its_action_without_greedy_decisions_and_ends_with_the_episode() -> None:
    ez, rng = explorer(max_repeat=50, exponent=0.5), np.random.default_rng(3)
    first = ez.act(0, np.zeros(1), 1.0, rng)  # exploring: a run starts
    left = ez.runs[0][1]
    assert left > 0  # with exponent 0.5, long runs are likely (seed chosen for one)
    # epsilon 0 would mean greedy, but the run goes on: the same action, no draws
    state = rng.bit_generator.state
    assert [ez.act(0, np.zeros(1), 0.0, rng) for _ in range(left)] == [first] * left
    assert rng.bit_generator.state == state
    assert ez.act(0, np.zeros(1), 0.0, rng) == GREEDY  # the run is over
    ez.act(1, np.zeros(1), 1.0, rng)
    ez.start_episode()
    assert ez.runs == {}


def test_with_runs_of_one_step_it_is_plain_epsilon_greedy() -> None:
    """Same actions as `DQNAgent.act` would pick, draw for draw, except for the extra length draw
    that exploring steps take (so compare with max_repeat 1: a single possible length)."""
    ez = explorer(max_repeat=1)
    a, b = np.random.default_rng(11), np.random.default_rng(11)
    mine = [ez.act(0, np.zeros(1), 0.3, a) for _ in range(500)]
    plain = []
    for _ in range(500):
        explore, action = b.random() < 0.3, int(b.integers(8))
        plain.append(action if explore else GREEDY)
        if explore:
            b.choice(1, p=[1.0])
    assert mine == plain


def test_the_option_is_off_by_default_and_checked(tmp_path) -> None:
    with Trainer.start(tmp_path, RunSpec(world="corridor.yaml"), tiny_config(), corridor_factory(),
                       progress=False) as trainer:
        assert trainer.explorer is None
    with Trainer.start(tmp_path, RunSpec(world="corridor.yaml"), tiny_config(explore_repeat_max=6), corridor_factory(),
                       progress=False) as trainer:
        assert trainer.explorer is not None and len(trainer.explorer.probabilities) == 6
        trainer.run_episode()  # flies with it
    with pytest.raises(ConfigError, match="explore_repeat_max"):
        tiny_config(explore_repeat_max=4, num_envs=2)
