"""Distilled policies: a shallow decision tree that flies like the greedy DQN (VIPER with DAgger).

Iteration 0 flies the network and records the states it visits; every later iteration flies the
newest tree instead, so the data grows where the tree actually goes (DAgger). Every recorded
state is labelled with the network's greedy action and weighted by what a wrong action could cost
there, max_a Q - min_a Q (VIPER): states where the network does not care count little. The tree is
refitted on all data so far. Each tree is scored on the next iteration's flight (fresh seeds it
was not fitted on), and the best one is kept: highest success, then fidelity, then return.

The kept tree and the network are then flown on the evaluation seeds of `sitl-bridge eval` (same
`seed` and `episodes` give the same episodes) through the same `rl/evaluation/evaluate.py` summary, so the
success rates compare like for like.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sitl_bridge.rl.analysis.tree_policy import TreePolicy, feature_labels, tree_rules, tree_text
from sitl_bridge.rl.common.drones_env import DronesEnv
from sitl_bridge.rl.evaluation.evaluate import EvalResult, evaluate_on, summarize
from sitl_bridge.rl.evaluation.rollout import rollout

QFunction = Callable[[np.ndarray], np.ndarray]
"""Q values of a batch of observations: (N, obs_dim) -> (N, n_actions)."""
Policy = Callable[[np.ndarray], int]

DISTILL_SEED_OFFSET = 2_000_029
"""Distillation flights use seeds apart from training's and evaluation's (`rollout.eval_seeds`)."""
ANALYSIS_EXTRA = "pip install 'sitl-bridge[analysis]'"


@dataclass
class Dataset:
    """Labelled states: what the network would do there and how much it matters."""

    states: np.ndarray
    """(N, obs_dim) observations."""
    actions: np.ndarray
    """(N,) the network's greedy action."""
    weights: np.ndarray
    """(N,) VIPER weights, max_a Q - min_a Q."""

    def __len__(self) -> int:
        return int(self.actions.shape[0])


def viper_weights(q: np.ndarray) -> np.ndarray:
    """VIPER's weight of each state (rows of `q`, (N, n_actions)): the Q-value gap between the
    best and the worst action, the most a wrong choice there can cost."""
    q = np.asarray(q, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] < 1:
        raise ValueError(f"Q values must be (states, actions), got shape {q.shape}")
    return q.max(axis=1) - q.min(axis=1)


def label(q_fn: QFunction, states: np.ndarray) -> Dataset:
    """`states` labelled with the greedy action of `q_fn` and weighted by its Q-value gap."""
    states = np.asarray(states, dtype=np.float32)
    q = np.asarray(q_fn(states), dtype=np.float64)
    return Dataset(states, np.argmax(q, axis=1).astype(np.int64), viper_weights(q))


def aggregate(data: Dataset | None, new: Dataset) -> Dataset:
    """DAgger's aggregation: the union of all labelled states so far (`data` None: just `new`)."""
    if data is None:
        return new
    return Dataset(np.concatenate([data.states, new.states]), np.concatenate([data.actions, new.actions]),
                   np.concatenate([data.weights, new.weights]))


def sample_weights(weights: np.ndarray) -> np.ndarray:
    """Weights for the fit: VIPER's, or uniform where the network is indifferent everywhere
    (all gaps 0), which would otherwise leave nothing to fit."""
    weights = np.asarray(weights, dtype=np.float64)
    return weights if weights.sum() > 0 else np.ones_like(weights)


def fit_tree(data: Dataset, max_depth: int, seed: int = 0) -> TreePolicy:
    """A decision tree of at most `max_depth` fitted to `data` (scikit-learn's CART, weighted)."""
    try:
        from sklearn.tree import DecisionTreeClassifier
    except ImportError:
        raise RuntimeError(f"distillation needs scikit-learn: {ANALYSIS_EXTRA}") from None
    if len(data) == 0:
        raise ValueError("no states to fit a tree to (every episode ended before its first step?)")
    classifier = DecisionTreeClassifier(max_depth=max_depth, random_state=seed)
    classifier.fit(data.states, data.actions, sample_weight=sample_weights(data.weights))
    return TreePolicy.from_sklearn(classifier)


def fidelity(tree: Policy | TreePolicy, data: Dataset) -> float:
    """Share of `data`'s states where the tree picks the network's action (unweighted)."""
    if len(data) == 0:
        return 0.0
    chosen = tree.predict(data.states) if isinstance(tree, TreePolicy) else np.array([tree(s) for s in data.states])
    return float(np.mean(chosen == data.actions))


class Recorder:
    """A policy that keeps every observation it is asked about (the states a flight visits)."""

    def __init__(self, policy: Policy) -> None:
        self.policy = policy
        self.states: list[np.ndarray] = []

    def __call__(self, obs: np.ndarray) -> int:
        self.states.append(np.asarray(obs, dtype=np.float32).reshape(-1))
        return self.policy(obs)

    def visited(self, obs_dim: int) -> np.ndarray:
        return np.stack(self.states) if self.states else np.zeros((0, obs_dim), dtype=np.float32)


def collection_seeds(seed: int, iteration: int, episodes: int) -> list[int]:
    """Reset seeds of one distillation iteration's flight."""
    sequence = np.random.SeedSequence([seed, DISTILL_SEED_OFFSET, iteration])
    return [int(s) for s in sequence.generate_state(episodes)]


@dataclass
class Candidate:
    """One iteration's tree, scored on the next iteration's flight (seeds it was not fitted on)."""

    iteration: int
    samples: int
    """Labelled states the tree was fitted on."""
    depth: int
    leaves: int
    fidelity: float
    success: float
    mean_return: float
    tree: TreePolicy = field(repr=False)

    def to_dict(self) -> dict[str, Any]:
        return {k: v for k, v in asdict(self).items() if k != "tree"}


def dagger(env: DronesEnv, q_fn: QFunction, teacher: Policy, *, max_depth: int = 6, iterations: int = 5,
           episodes: int = 20, seed: int = 0, world: str = "",
           on_candidate: Callable[[Candidate], None] | None = None) -> list[Candidate]:
    """`iterations` trees, each fitted on every state labelled so far and scored on a fresh flight."""
    if iterations < 1 or episodes < 1:
        raise ValueError(f"iterations and episodes must be at least 1, got {iterations} and {episodes}")
    data: Dataset | None = None
    tree: TreePolicy | None = None
    candidates: list[Candidate] = []
    for i in range(iterations + 1):
        recorder = Recorder(teacher if tree is None else tree)
        traces = rollout(env, recorder, collection_seeds(seed, i, episodes))
        labelled = label(q_fn, recorder.visited(env.obs_dim))
        if tree is not None:  # the previous tree just flew seeds it was not fitted on
            flown = summarize(world, episodes, traces)
            candidate = Candidate(i - 1, len(data), tree.depth, tree.leaves, fidelity(tree, labelled),
                                  flown.success_rate, flown.mean_reward, tree)
            candidates.append(candidate)
            if on_candidate is not None:
                on_candidate(candidate)
        if i == iterations:
            break
        data = aggregate(data, labelled)
        tree = fit_tree(data, max_depth, seed)
    return candidates


def best_candidate(candidates: list[Candidate]) -> Candidate:
    """Highest held-out success, then fidelity, then mean return; the earliest among equals."""
    return max(reversed(candidates), key=lambda c: (c.success, c.fidelity, c.mean_return))


@dataclass
class DistillResult:
    """A distilled tree next to the network it imitates, on the same evaluation episodes."""

    world: str
    frame: str
    episodes: int
    depth: int
    leaves: int
    fidelity: float
    """Share of the network's actions the tree repeats on the states the tree visits."""
    fidelity_network_states: float
    """The same share on the states the network visits."""
    success: float
    network_success: float
    mean_return: float
    network_return: float
    crash: float
    network_crash: float
    chosen_iteration: int
    candidates: list[dict[str, Any]]
    text: str
    rules: dict[str, Any] = field(repr=False)
    """The tree as a rules document (`rules_yaml()`)."""
    tree: TreePolicy = field(repr=False)

    def to_dict(self) -> dict[str, Any]:
        """Every field but the tree and its rules (JSON-ready)."""
        return {k: v for k, v in asdict(self).items() if k not in ("tree", "rules")}

    def rules_yaml(self) -> str:
        import yaml

        return yaml.safe_dump(self.rules, sort_keys=False, allow_unicode=True, width=120, default_flow_style=None)

    def summary(self) -> str:
        return (f"{self.world}: tree depth {self.depth}, {self.leaves} leaves (iteration "
                f"{self.chosen_iteration}); fidelity {self.fidelity:.1%} on the tree's states, "
                f"{self.fidelity_network_states:.1%} on the network's\n"
                f"  tree:    success {self.success:.0%}, crash {self.crash:.0%}, mean return "
                f"{self.mean_return:.1f}\n"
                f"  network: success {self.network_success:.0%}, crash {self.network_crash:.0%}, mean return "
                f"{self.network_return:.1f}   ({self.episodes} evaluation episodes each)\n\n{self.text}")


def _flown(env: DronesEnv, policy: Policy, world: str, episodes: int, seed: int) -> tuple[EvalResult, np.ndarray]:
    recorder = Recorder(policy)
    result, _traces = evaluate_on(env, recorder, world=world, episodes=episodes, seed=seed)
    return result, recorder.visited(env.obs_dim)


def distill_policy(env: DronesEnv, q_fn: QFunction, teacher: Policy, *, layout: dict[str, slice],
                   words: dict[int, str] | None = None,
                   frame: str = "world", world: str = "", covers: list[str] | None = None,
                   max_depth: int = 6, iterations: int = 5, episodes: int = 20, seed: int = 0,
                   source: str = "", on_candidate: Callable[[Candidate], None] | None = None) -> DistillResult:
    """Distil `teacher` (the greedy policy of `q_fn`) into a tree in `env` and compare the two on
    `episodes` evaluation episodes (`rl.evaluation.rollout.eval_seeds(seed, episodes)`)."""
    candidates = dagger(env, q_fn, teacher, max_depth=max_depth, iterations=iterations, episodes=episodes,
                        seed=seed, world=world, on_candidate=on_candidate)
    best = best_candidate(candidates)
    tree = best.tree
    tree_result, tree_states = _flown(env, tree, world, episodes, seed)
    network_result, network_states = _flown(env, teacher, world, episodes, seed)
    labels = feature_labels(layout, env.obs_dim)
    fid = fidelity(tree, label(q_fn, tree_states))
    fid_network = fidelity(tree, label(q_fn, network_states))
    name = f"distilled tree of {Path(source or world).name}"
    rules = tree_rules(tree, labels, frame=frame, name=name, covers=covers or [],
                       source=f"VIPER distillation of {source or world}: depth {tree.depth}, fidelity "
                              f"{fid:.1%}, success {tree_result.success_rate:.0%} (network "
                              f"{network_result.success_rate:.0%}) over {episodes} episodes, seed {seed}")
    return DistillResult(
        world=world, frame=frame, episodes=episodes, depth=tree.depth, leaves=tree.leaves,
        fidelity=fid, fidelity_network_states=fid_network,
        success=tree_result.success_rate, network_success=network_result.success_rate,
        mean_return=tree_result.mean_reward, network_return=network_result.mean_reward,
        crash=tree_result.crash_rate, network_crash=network_result.crash_rate,
        chosen_iteration=best.iteration, candidates=[c.to_dict() for c in candidates],
        text=tree_text(tree, labels, frame, words), rules=rules, tree=tree)


def network_q(network: Any) -> QFunction:
    """Batched Q values of a `QNetwork` (no gradients)."""
    import torch

    def q(states: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            batch = torch.as_tensor(np.asarray(states, dtype=np.float32).reshape(len(states), -1))
            return network(batch).numpy() if len(states) else np.zeros((0, network.shape.n_actions))

    return q


def distill_run(run_dir: str | Path, *, world: str | Path | None = None, max_depth: int = 6,
                iterations: int = 5, episodes: int = 20, seed: int = 0, autopilot: str = "direct",
                on_candidate: Callable[[Candidate], None] | None = None) -> DistillResult:
    """Distil the greedy policy of a run directory (or checkpoint) in its own scenario, or `world`."""
    from sitl_bridge.envs.features import index_words, observation_layout
    from sitl_bridge.envs.scenario import load_scenario
    from sitl_bridge.rl.common.drones_env import scenario_env_factory
    from sitl_bridge.rl.learner.policy import policy_from_checkpoint, require_discrete
    from sitl_bridge.rl.training.run_dir import read_run_files, run_dir_of, run_scenario

    policy = require_discrete(policy_from_checkpoint(run_dir), "distillation")
    own = world is None
    world = Path(world) if world is not None else run_scenario(run_dir)
    covers = [world.name]
    home = run_dir_of(run_dir)
    if own and home is not None:  # the run's copy is scenario.yaml; it covers the file it was made from
        covers = [Path(read_run_files(home)[0].world).name]
    scenario = load_scenario(world)
    env = DronesEnv(scenario_env_factory(world, autopilot)(seed))
    try:
        if env.obs_dim != policy.obs_dim:
            raise ValueError(f"{policy.source}: the network takes {policy.obs_dim} observation values, "
                             f"{world} gives {env.obs_dim}")
        return distill_policy(env, network_q(policy.network), policy, layout=observation_layout(scenario.task.observation),
                              words=index_words(scenario.task.observation),
                              frame=scenario.task.action.frame, world=str(world), covers=covers,
                              max_depth=max_depth, iterations=iterations, episodes=episodes, seed=seed,
                              source=str(home or run_dir), on_candidate=on_candidate)
    finally:
        env.close()

