"""DQN improvements: each option's maths against a hand computation, and a run
with all of them on resumes exactly (priorities and normaliser statistics restored)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from test_rl_helpers import corridor_factory, tiny_config

from sitl_bridge.errors import ConfigError
from sitl_bridge.rl.learner.config import TrainConfig
from sitl_bridge.rl.learner.dqn import (
    Batch,
    DQNAgent,
    NetworkShape,
    QNetwork,
    dueling_q,
    td_targets,
)
from sitl_bridge.rl.learner.dqn_learner import DQNLearner
from sitl_bridge.rl.learner.normalizer import RunningNorm
from sitl_bridge.rl.learner.nstep import NStepFolder, Step
from sitl_bridge.rl.learner.prioritized import (
    Priorities,
    importance_weights,
    sampling_probabilities,
)
from sitl_bridge.rl.learner.replay_buffer import ReplayBuffer
from sitl_bridge.rl.training.run_dir import RunSpec
from sitl_bridge.rl.training.trainer import Trainer, read_run_records


# --- n-step -------------------------------------------------------------------------------------
def _episode(rewards: list[float], terminated_at_end: bool) -> list[Step]:
    n = len(rewards)
    return [Step(t, t, r, t + 1, terminated_at_end and t == n - 1) for t, r in enumerate(rewards)]


@pytest.mark.parametrize("terminated", [True, False])
def test_n_step_rows_match_a_hand_computation(terminated: bool) -> None:
    gamma, rewards = 0.9, [1.0, 2.0, 3.0, 4.0]
    folder = NStepFolder(3, gamma)
    rows = []
    for k, step in enumerate(_episode(rewards, terminated)):
        rows += folder.push(0, step, episode_over=k == len(rewards) - 1)
    assert [r.obs for r in rows] == [0, 1, 2, 3]
    assert [r.next_obs for r in rows] == [3, 4, 4, 4]
    expected = [1 + 0.9 * 2 + 0.81 * 3, 2 + 0.9 * 3 + 0.81 * 4, 3 + 0.9 * 4, 4.0]
    assert [r.reward for r in rows] == pytest.approx(expected)
    # gamma * (1 - terminated) must be gamma^m, or 0 after a real end.
    bootstrap = [gamma * (1 - r.terminated) for r in rows]
    if terminated:
        assert bootstrap == pytest.approx([0.9 ** 3, 0, 0, 0])
    else:  # truncated by the step limit: the tails bootstrap with their shorter horizon
        assert bootstrap == pytest.approx([0.9 ** 3, 0.9 ** 3, 0.9 ** 2, 0.9])


def test_n_step_target_through_td_targets_equals_the_n_step_formula() -> None:
    gamma = 0.8
    folder = NStepFolder(2, gamma)
    steps = [Step(np.zeros(1), 0, 1.0, np.ones(1), False), Step(np.ones(1), 0, 5.0, np.full(1, 2.0), False)]
    row = folder.push(0, steps[0], False) + folder.push(0, steps[1], False)
    assert len(row) == 1
    constant = torch.nn.Linear(1, 2)
    torch.nn.init.zeros_(constant.weight)
    torch.nn.init.constant_(constant.bias, 10.0)  # Q(s', .) = 10
    y = td_targets(constant, constant, torch.tensor([row[0].reward]), torch.zeros(1, 1),
                   torch.tensor([row[0].terminated]), gamma)
    assert float(y) == pytest.approx(1.0 + 0.8 * 5.0 + 0.8 ** 2 * 10.0)


def test_n_step_keeps_drones_apart() -> None:
    folder = NStepFolder(2, 0.5)
    assert folder.push(0, Step("a0", 0, 1.0, "a1", False), False) == []
    assert folder.push(1, Step("b0", 0, 7.0, "b1", True), False)[0].reward == 7.0
    row = folder.push(0, Step("a1", 0, 2.0, "a2", False), False)[0]
    assert (row.obs, row.next_obs, row.reward) == ("a0", "a2", 2.0)


# --- dueling ------------------------------------------------------------------------------------
def test_dueling_aggregation() -> None:
    value = torch.tensor([[2.0], [-1.0]])
    advantage = torch.tensor([[1.0, 2.0, 3.0], [0.0, 0.0, 3.0]])
    q = dueling_q(value, advantage)
    assert torch.allclose(q, torch.tensor([[1.0, 2.0, 3.0], [-2.0, -2.0, 1.0]]))
    net = QNetwork(NetworkShape(4, 3, 3, 8, dueling=True))
    q = net(torch.randn(5, 4))
    features = net.net(torch.zeros(1, 4))
    assert q.shape == (5, 3)
    # Mean over actions of Q equals V: the advantage stream is centred.
    assert torch.allclose(net(torch.zeros(1, 4)).mean(dim=1), net.value(features).squeeze(1), atol=1e-6)


# --- prioritized replay -------------------------------------------------------------------------
def test_per_probabilities_and_importance_weights() -> None:
    p = np.array([1.0, 2.0, 4.0, 1.0])
    probs = sampling_probabilities(p, 0.5)
    expected = np.sqrt(p) / np.sqrt(p).sum()
    assert probs == pytest.approx(expected)
    w = importance_weights(probs, np.array([0, 2]), beta=0.4)
    raw = (4 * expected) ** -0.4
    assert w == pytest.approx(raw[[0, 2]] / raw.max())
    assert sampling_probabilities(p, 0.0) == pytest.approx(np.full(4, 0.25))  # alpha 0: uniform


def test_per_sampling_follows_priorities_and_updates() -> None:
    pri = Priorities(4, alpha=1.0, epsilon=0.01)
    replay = ReplayBuffer(4, 1, pri)
    replay.add_rows(replay.make_rows(np.zeros((4, 1)), np.zeros(4), np.zeros(4), np.zeros((4, 1)), np.zeros(4)))
    assert pri.values.tolist() == [1.0] * 4  # new rows: max priority
    pri.update(np.array([0, 1, 2, 3]), np.array([0.99, -2.99, 0.0, 0.0]))
    assert pri.values == pytest.approx([1.0, 3.0, 0.01, 0.01])
    assert pri.max_priority == pytest.approx(3.0)
    rng = np.random.default_rng(0)
    batch = replay.sample_prioritized(20_000, 1.0, rng)
    share = np.bincount(batch.slots, minlength=4) / 20_000
    assert share == pytest.approx(pri.values / pri.values.sum(), abs=0.01)
    assert float(batch.weights.max()) == pytest.approx(1.0)


def test_per_sampling_draws_bit_for_bit_what_numpy_choice_drew() -> None:
    """The cached powers and the inlined draw give exactly the slots and weights of the plain
    formula: the power of every priority, then rng.choice(p=...)."""
    pri = Priorities(500, alpha=0.6, epsilon=1e-3)
    data = np.random.default_rng(7)
    rng, reference_rng = np.random.default_rng(3), np.random.default_rng(3)
    filled = 0
    for _ in range(60):
        added = data.integers(1, 40)
        pri.added((filled + np.arange(added)) % 500)
        filled = min(filled + added, 500)
        slots, weights = pri.sample(filled, 64, 0.4, rng)
        probabilities = sampling_probabilities(pri.values[:filled], 0.6)
        expected = reference_rng.choice(filled, size=64, p=probabilities)
        assert np.array_equal(slots, expected)
        assert np.array_equal(weights, importance_weights(probabilities, expected, 0.4))
        pri.update(slots, data.normal(scale=data.uniform(0.01, 30.0), size=64))  # duplicates included
    restored = Priorities(500, alpha=0.6, epsilon=1e-3)
    restored.restore(pri.values.copy(), pri.max_priority)
    assert np.array_equal(restored.sample(filled, 64, 0.4, np.random.default_rng(1))[0],
                          pri.sample(filled, 64, 0.4, np.random.default_rng(1))[0])


def test_importance_weights_scale_the_loss() -> None:
    from sitl_bridge.rl.learner.dqn import dqn_loss_and_errors

    net = torch.nn.Linear(1, 2)
    torch.nn.init.zeros_(net.weight)
    torch.nn.init.zeros_(net.bias)
    batch = Batch(torch.zeros(2, 1), torch.zeros(2), torch.tensor([1.0, 3.0]), torch.zeros(2, 1),
                  torch.ones(2), weights=torch.tensor([1.0, 0.5]))
    loss, errors = dqn_loss_and_errors(net, net, batch, 0.9)
    assert errors.tolist() == [1.0, 3.0]
    assert float(loss.detach()) == pytest.approx((1.0 * 1.0 + 0.5 * 9.0) / 2)


# --- observation normalisation -------------------------------------------------------------------
def test_running_norm_matches_numpy_over_batches() -> None:
    rng = np.random.default_rng(1)
    data = rng.normal([3.0, -2.0], [0.5, 4.0], size=(300, 2))
    norm = RunningNorm(2)
    for chunk in np.array_split(data, [1, 7, 100, 250]):
        norm.update(torch.as_tensor(chunk))
    assert norm.mean.numpy() == pytest.approx(data.mean(axis=0))
    assert norm.var.numpy() == pytest.approx(data.var(axis=0))
    assert float(norm.count) == 300
    out = norm(torch.as_tensor(data, dtype=torch.float32)).numpy()
    assert out.mean(axis=0) == pytest.approx([0, 0], abs=1e-4)
    assert out.std(axis=0) == pytest.approx([1, 1], abs=1e-3)


def test_normaliser_statistics_travel_with_the_weights() -> None:
    net = QNetwork(NetworkShape(2, 3, 2, 4, normalize=True))
    net.norm.update(torch.tensor([[1.0, 2.0], [3.0, 6.0]]))
    copy = QNetwork(NetworkShape(2, 3, 2, 4, normalize=True))
    copy.load_state_dict(net.state_dict())
    assert copy.norm.mean.tolist() == [2.0, 4.0]


# --- gradient clipping --------------------------------------------------------------------------
def test_gradient_norm_is_clipped() -> None:
    torch.manual_seed(0)
    config = TrainConfig(optimizer="sgd", learning_rate=1.0, max_grad_norm=0.5, batch_size=2)
    agent = DQNAgent(NetworkShape(3, 2, 2, 8), config)
    before = [p.detach().clone() for p in agent.online.parameters()]
    batch = Batch(torch.ones(2, 3), torch.zeros(2), torch.tensor([1e3, -1e3]), torch.ones(2, 3), torch.ones(2))
    agent.update(batch)
    # SGD with rate 1: the parameter change is minus the (clipped) gradient.
    delta = torch.cat([(p.detach() - b).reshape(-1) for p, b in zip(agent.online.parameters(), before, strict=True)])
    assert float(delta.norm()) == pytest.approx(0.5, rel=1e-4)


# --- all options on: resume is exact ------------------------------------------------------------
def test_run_with_every_option_resumes_exactly(tmp_path: Path) -> None:
    options = dict(n_step=3, dueling=True, prioritized_replay=True, normalize_observations=True,
                   max_grad_norm=5.0, layers=3)
    spec = RunSpec(world="corridor.yaml", seed=3)
    with Trainer.start(tmp_path / "ref", spec, tiny_config(episodes=6, **options), corridor_factory(),
                       progress=False) as ref:
        ref.train()
    with Trainer.start(tmp_path / "cut", spec, tiny_config(episodes=6, **options), corridor_factory(),
                       progress=False) as cut:
        for _ in range(3):  # the same run, interrupted after 3 episodes
            cut.run_episode()
            cut.save_checkpoint()
    with Trainer.resume(cut.run_dir, corridor_factory(), episodes=6, progress=False) as resumed:
        assert resumed.replay.priorities is not None
        assert resumed.agent.online.norm is not None and float(resumed.agent.online.norm.count) > 0
        resumed.train()
        assert np.array_equal(resumed.replay.priorities.values, ref.replay.priorities.values)
        assert torch.equal(resumed.agent.online.norm.mean, ref.agent.online.norm.mean)
    a, b = read_run_records(ref.run_dir), read_run_records(resumed.run_dir)
    keys = ("episode", "drone", "actions", "reward", "mean_loss", "global_step")
    assert [[r[k] for k in keys] for r in a] == [[r[k] for k in keys] for r in b]


# --- how often the learner updates --------------------------------------------------------------
def _learner_with_rows(rows: int, **config: object) -> DQNLearner:
    cfg = TrainConfig(batch_size=4, replay_capacity=100, layers=2, hidden_units=8, **config)
    torch.manual_seed(0)
    learner = DQNLearner(NetworkShape(3, 2, 2, 8), cfg, torch.device("cpu"), np.random.default_rng(0))
    data = np.random.default_rng(1)
    learner.remember(learner.replay.make_rows(data.normal(size=(rows, 3)), data.integers(0, 2, rows),
                                              data.normal(size=rows), data.normal(size=(rows, 3)), np.zeros(rows)))
    return learner


@pytest.mark.parametrize(("train_every", "gradient_steps", "step_batches", "expected"), [
    (1, 1, [1, 1, 1], 3), (3, 1, [1, 1, 1, 1, 1, 1, 1], 2), (2, 3, [5, 1], 9), (4, 2, [3, 3, 3], 4)])
def test_updates_follow_train_every_and_gradient_steps(train_every: int, gradient_steps: int,
                                                       step_batches: list[int], expected: int) -> None:
    learner = _learner_with_rows(10, train_every=train_every, gradient_steps=gradient_steps)
    losses: list[float] = []
    for steps in step_batches:  # a vector step counts several env steps at once
        learner.after_steps(steps, losses)
    assert learner.updates == expected == len(losses)


def test_no_update_before_the_replay_holds_a_batch() -> None:
    learner = _learner_with_rows(3, gradient_steps=4)
    losses: list[float] = []
    learner.after_steps(5, losses)
    assert learner.updates == 0 and learner.global_step == 5
    with pytest.raises(ConfigError, match="gradient_steps"):
        learner.config.replace(gradient_steps=0)


def test_training_sets_torch_to_one_intra_and_one_inter_op_thread(tmp_path: Path) -> None:
    """Where training starts, torch gets `torch_threads` intra-op threads and one inter-op thread
    (a fresh process: the inter-op pool can be sized only before its first use)."""
    import subprocess
    import sys

    code = ("import torch; from sitl_bridge.rl.learner.torch_threads import use_torch_threads; "
            "use_torch_threads(1); use_torch_threads(1); "  # a second call (another run in the process) is harmless
            "print(torch.get_num_threads(), torch.get_num_interop_threads())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.split() == ["1", "1"]
