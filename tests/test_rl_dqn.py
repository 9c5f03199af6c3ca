"""The DQN maths on hand-computed examples: TD targets, losses, epsilon and learning-rate schedules,
network shape, and one real update."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import nn

from sitl_bridge.errors import ConfigError
from sitl_bridge.rl.learner.config import TrainConfig, field_docs
from sitl_bridge.rl.learner.dqn import (
    Batch,
    DQNAgent,
    NetworkShape,
    QNetwork,
    dqn_loss,
    epsilon_at,
    learning_rate_at,
    td_targets,
)
from sitl_bridge.rl.learner.replay_buffer import ReplayBuffer


def table_q(rows: list[list[float]]) -> nn.Module:
    """A 'network' whose Q values for one-hot state s are rows[s] (a bias-free Linear layer)."""
    layer = nn.Linear(len(rows), len(rows[0]), bias=False)
    with torch.no_grad():
        layer.weight.copy_(torch.tensor(rows, dtype=torch.float32).T)
    return layer


S0, S1 = [1.0, 0.0], [0.0, 1.0]
# Online: s0 -> [1, 2, 3], s1 -> [4, 0, 1];  target: s0 -> [10, 20, 5], s1 -> [7, 8, 9]
ONLINE = [[1.0, 2.0, 3.0], [4.0, 0.0, 1.0]]
TARGET = [[10.0, 20.0, 5.0], [7.0, 8.0, 9.0]]
# (s0, a=1, r=1, s'=s1, not terminal) and (s1, a=0, r=-2, s'=s0, terminal); gamma 0.5
BATCH = Batch(obs=torch.tensor([S0, S1]), actions=torch.tensor([1, 0]), rewards=torch.tensor([1.0, -2.0]),
              next_obs=torch.tensor([S1, S0]), terminated=torch.tensor([0.0, 1.0]))


def test_double_dqn_target_uses_online_argmax_and_target_value() -> None:
    # a* = argmax online(s1) = 0 -> target(s1, 0) = 7 -> y = 1 + 0.5 * 7 = 4.5; terminal: y = r = -2
    y = td_targets(table_q(ONLINE), table_q(TARGET), BATCH.rewards, BATCH.next_obs, BATCH.terminated, 0.5, True)
    assert y.tolist() == [4.5, -2.0]


def test_plain_dqn_target_takes_max_of_target() -> None:
    # max target(s1) = 9 -> y = 1 + 0.5 * 9 = 5.5
    y = td_targets(table_q(ONLINE), table_q(TARGET), BATCH.rewards, BATCH.next_obs, BATCH.terminated, 0.5, False)
    assert y.tolist() == [5.5, -2.0]


@pytest.mark.parametrize(("loss", "double", "expected"), [
    ("mse", True, (2.5**2 + 6.0**2) / 2),       # Q taken: online(s0,1)=2, online(s1,0)=4; errors -2.5, 6
    ("mse", False, (3.5**2 + 6.0**2) / 2),
    ("mae", True, (2.5 + 6.0) / 2),
    ("huber", True, ((2.5 - 0.5) + (6.0 - 0.5)) / 2),  # |e| > 1: |e| - 0.5
])
def test_loss_on_hand_computed_batch(loss: str, double: bool, expected: float) -> None:
    value = dqn_loss(table_q(ONLINE), table_q(TARGET), BATCH, gamma=0.5, loss=loss, double=double)
    assert value.item() == pytest.approx(expected)


def test_gradient_reaches_online_network_only() -> None:
    online, target = table_q(ONLINE), table_q(TARGET)
    dqn_loss(online, target, BATCH, gamma=0.5).backward()
    assert target.weight.grad is None
    # d/dQ(s0,1) of mean((Q - y)^2) = 2 * (2 - 4.5) / 2 = -2.5; d/dQ(s1,0) = 2 * 6 / 2 = 6
    grad = online.weight.grad.T  # [state, action]
    assert grad[0, 1].item() == pytest.approx(-2.5)
    assert grad[1, 0].item() == pytest.approx(6.0)
    assert grad.abs().sum().item() == pytest.approx(8.5)


def test_epsilon_schedule_is_thesis_equation_16() -> None:
    assert epsilon_at(0, 1.0, 0.0, 5e-5) == 1.0
    assert epsilon_at(20_000, 1.0, 0.0, 5e-5) == pytest.approx(math.exp(-1.0))
    assert epsilon_at(10**9, 0.6, 0.05, 5e-5) == pytest.approx(0.05)
    assert epsilon_at(1000, 0.8, 0.2, 1e-3) == pytest.approx(0.2 + 0.6 * math.exp(-1.0))


def test_learning_rate_schedule_geometric_start_to_end() -> None:
    assert learning_rate_at(0, 101, 1e-4, 1e-7) == pytest.approx(1e-4)
    assert learning_rate_at(50, 101, 1e-4, 1e-7) == pytest.approx(10**-5.5)
    assert learning_rate_at(100, 101, 1e-4, 1e-7) == pytest.approx(1e-7)
    assert learning_rate_at(70, 101, 5e-4, 0.0) == 5e-4  # no end: constant


def test_network_has_configured_layers_and_prelu() -> None:
    net = QNetwork(NetworkShape(obs_dim=5, n_actions=8, layers=4, hidden_units=32))
    linears = [m for m in net.modules() if isinstance(m, nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [(5, 32), (32, 32), (32, 32), (32, 8)]
    assert sum(isinstance(m, nn.PReLU) for m in net.modules()) == 3
    assert net(torch.zeros(5)).shape == (8,)
    assert net(torch.zeros(3, 5)).shape == (3, 8)


@pytest.mark.parametrize("optimizer", ["adam", "adamax", "sgd", "rmsprop"])
def test_updates_lower_the_loss_on_a_fixed_batch(optimizer: str) -> None:
    torch.manual_seed(0)
    config = TrainConfig(gamma=0.0, learning_rate=1e-2, optimizer=optimizer, layers=2, hidden_units=16, batch_size=4)
    agent = DQNAgent(NetworkShape(2, 3, 2, 16), config)
    replay = ReplayBuffer(8, 2)
    replay.add_rows(replay.make_rows(np.eye(2, dtype=np.float32), np.array([1, 2]), np.array([1.0, -1.0]),
                                     np.eye(2, dtype=np.float32), np.array([1.0, 1.0])))
    batch = replay.sample(4, np.random.default_rng(0))
    first = agent.update(batch)
    for _ in range(200):
        last = agent.update(batch)
    assert last < 0.1 * first


def test_epsilon_greedy_extremes() -> None:
    agent = DQNAgent(NetworkShape(2, 8, 2, 8), TrainConfig(layers=2, hidden_units=8))
    rng = np.random.default_rng(1)
    greedy = int(np.argmax(agent.q_values(np.zeros(2, dtype=np.float32))))
    assert {agent.act(np.zeros(2, dtype=np.float32), 0.0, rng) for _ in range(20)} == {greedy}
    assert len({agent.act(np.zeros(2, dtype=np.float32), 1.0, rng) for _ in range(200)}) == 8


def test_replay_ring_overwrites_oldest() -> None:
    replay = ReplayBuffer(3, 1)
    for value in range(5):
        replay.add_rows(replay.make_rows(np.full((1, 1), value), np.array([value]), np.zeros(1),
                                         np.zeros((1, 1)), np.zeros(1)))
    assert len(replay) == 3 and replay.total_added == 5
    assert sorted(replay.rows["action"].tolist()) == [2, 3, 4]


def test_config_rejects_bad_values_and_documents_fields() -> None:
    with pytest.raises(ConfigError, match="optimizer: expected one of adam"):
        TrainConfig(optimizer="adagrad")
    with pytest.raises(ConfigError, match="gamma"):
        TrainConfig(gamma=1.5)
    docs = field_docs()
    assert set(docs) == set(TrainConfig.__dataclass_fields__)
    assert "exp(-lambda * steps)" in docs["epsilon_max"]


def test_config_errors_name_file_key_and_flag(tmp_path) -> None:  # noqa: ANN001
    from sitl_bridge.rl.learner.config import apply_overrides, load_train_config

    path = tmp_path / "w.yaml"
    path.write_text("world: {}\ntrain:\n  gamma: 2\n")
    with pytest.raises(ConfigError, match=r"w\.yaml: train\.gamma: expected a number in \[0, 1\], got 2"):
        load_train_config(path)
    path.write_text("train:\n  gama: 0.9\n")
    with pytest.raises(ConfigError, match=r"train\.gama: unknown key"):
        load_train_config(path)
    path.write_text("train:\n  batch_size: 32\n  layers: 3\n")
    config = load_train_config(path, {"layers": 5, "gamma": None})
    assert (config.batch_size, config.layers, config.gamma) == (32, 5, TrainConfig().gamma)
    with pytest.raises(ConfigError, match="command line: --learning-rate: expected a positive number"):
        apply_overrides(config, {"learning_rate": -1.0})
