"""DQN hyperparameters: one dataclass, read from a scenario's `train:` section, overridable on the
command line.

Each field's docstring is its documentation and becomes its `--help` text (read from this file's
source, CleanRL/tyro style), so the docs cannot drift from the code. Example `train:` section::

    train:
      episodes: 1500
      gamma: 0.9
      learning_rate: 0.00077
      batch_size: 400
      target_update_period: 100
      layers: 10
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import math
import re
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any

from sitl_bridge.errors import ConfigError, Node, load_yaml
from sitl_bridge.rl.learner.sb3_arguments import MissingExtra, check_arguments
from sitl_bridge.world.lookup import world_file

OPTIMIZERS = ("adam", "adamax", "sgd", "rmsprop")
LOSSES = ("mse", "huber", "mae")
TARGET_UPDATE_UNITS = ("steps", "episodes")
ALGORITHMS = ("dqn", "ppo", "sac", "td3")
"""`dqn` is the project's own learner; the others are Stable-Baselines3's (`rl/learner/sb3_models.py`)."""
SB3_SECTIONS = ("ppo", "sac", "td3")
"""`train:` keys holding one SB3 algorithm's constructor arguments each."""
RUN_WIDE = frozenset({"algorithm", "experiment", "episodes", "eval_episodes", "eval_every", "stop_on_success",
                      "stop_confirm_episodes", "checkpoints_kept", "success_window", "torch_threads", "device",
                      "num_envs", *SB3_SECTIONS})
"""Fields every algorithm reads; the others are DQN's own hyperparameters."""


SAFE_NAME = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9_.-]{0,63}")
"""Names that become parts of paths (the experiment's name in run directory names)."""
MAX_EPISODES = 10_000_000
MAX_REPLAY_ROWS = 20_000_000
"""Replay rows at most (about 10 GB with the largest shipped observation of 65 values)."""


@dataclass(frozen=True)
class TrainConfig:
    """Everything that decides how a DQN run learns (thesis Tables 4-8)."""

    algorithm: str = "dqn"
    """Learning algorithm: dqn (the project's own, every field below), or ppo, sac, td3
    (Stable-Baselines3, the `sb3` extra; their hyperparameters are the mapping under the
    algorithm's own key, e.g. `sac: {learning_rate: 0.0003}`)."""
    experiment: str = "dqn"
    """Experiment name, the second part of the run directory name (an SB3 run left at `dqn`
    is named after its algorithm)."""
    episodes: int = 1000
    """The most training episodes the run takes (a cap: with stop_on_success and eval_every set,
    training stops at the first periodic greedy evaluation that reaches it)."""
    gamma: float = 0.9
    """Discount factor of future rewards."""
    epsilon_max: float = 1.0
    """Exploration rate at step 0: eps = eps_min + (eps_max - eps_min) * exp(-lambda * steps)."""
    epsilon_min: float = 0.0
    """Exploration rate the schedule decays to."""
    epsilon_decay: float = 5e-5
    """lambda of the exponential epsilon schedule, per environment step (thesis: 3e-5..6e-5)."""
    explore_repeat_max: int = 1
    """Temporally extended exploration (ez-greedy, `rl/learner/exploration.py`): an exploring step
    repeats its random action for 1..this many steps (zeta-distributed); 1 = plain epsilon-greedy."""
    explore_repeat_exponent: float = 2.0
    """ez-greedy: P(run of n steps) proportional to n^-this (larger: shorter runs)."""
    guided_explore_episodes: int = 0
    """Goal-seeking exploration in the first this many episodes (0 = off): each step there takes,
    with probability epsilon x `guided_explore_share`, the action of a guide that follows the
    shortest obstacle-free path to the goal (`envs/path_guide.py`) instead of the epsilon-greedy
    one, so that the replay holds goals before the values settle on crashing early
    (docs/findings.md, why seeds collapse)."""
    guided_explore_share: float = 0.5
    """Share of the exploring (epsilon) steps of the guided episodes that follow the guide."""
    transfer_epsilon_max: float = 0.6
    """epsilon_max used instead when the run starts from another run's network (thesis: 0.45-0.8)."""
    transfer_replay: bool = False
    """Starting from another run's network, also start with that run's replay (its transitions
    as of its newest checkpoint): for fine-tuning in the same scenario on another backend, where
    the first updates would otherwise fit a few new episodes and undo what was learned."""
    learning_rate: float = 1e-3
    """Learning rate (at the start when learning_rate_end is set)."""
    learning_rate_end: float = 0.0
    """Learning rate reached at the last episode, geometric interpolation; 0 = constant rate."""
    optimizer: str = "adam"
    """Optimizer: adam, adamax, sgd or rmsprop."""
    loss: str = "mse"
    """Loss between Q(s, a) and its target: mse, huber or mae."""
    batch_size: int = 64
    """Transitions per gradient update, sampled uniformly from the replay."""
    learning_starts: int = 0
    """Transitions collected before the first update (at least batch_size)."""
    train_every: int = 1
    """Gradient updates are due every this many environment steps (each drone's and each copy's
    step counts); raise it to spend less of a run in the learner."""
    gradient_steps: int = 1
    """Gradient updates made each time updates are due (every train_every env steps)."""
    num_envs: int = 1
    """Copies of the scenario flown at once (sitl_bridge.make_vec_env, single-drone scenarios):
    episodes run in waves of this many, one network call picks all their actions, and each wave
    is checkpointed when its last episode ends (1 = one episode at a time)."""
    target_update_period: int = 100
    """Copy the online network into the target network every this many steps (or episodes)."""
    target_update_unit: str = "steps"
    """Unit of target_update_period: steps (gradient updates) or episodes."""
    double_dqn: bool = True
    """Double DQN: the online network picks the next action, the target network values it."""
    replay_capacity: int = 100_000
    """Transitions kept in the experience replay (oldest dropped first; thesis: O needs >= 60k)."""
    layers: int = 4
    """Linear layers of the Q network, output layer included (the thesis's "number of layers")."""
    hidden_units: int = 64
    """Width of every hidden layer (PReLU activations)."""
    max_grad_norm: float = 0.0
    """Clip the gradient norm to this value; 0 = no clipping."""
    n_step: int = 1
    """n-step returns: each target sums n discounted rewards before bootstrapping (1 = thesis)."""
    dueling: bool = False
    """Dueling network head: Q(s, a) = V(s) + A(s, a) - mean of A over the actions."""
    prioritized_replay: bool = False
    """Prioritized replay: sample transitions by |TD error|^per_alpha, weight by importance."""
    per_alpha: float = 0.6
    """Prioritized replay: how strongly priorities shape sampling (0 = uniform)."""
    per_beta: float = 0.4
    """Prioritized replay: importance-weight exponent at the start, annealed to 1 at the end."""
    per_epsilon: float = 1e-3
    """Prioritized replay: added to |TD error| so that no transition has zero probability."""
    normalize_observations: bool = False
    """Normalise the network's inputs by the running mean and variance of the observations."""
    eval_episodes: int = 20
    """Greedy evaluation episodes after training and at every eval_every (0 = none)."""
    eval_every: int = 0
    """Also evaluate greedily every this many training episodes (0 = only at the end)."""
    stop_on_success: float = 0.0
    """Stop early once a periodic greedy evaluation reaches this success rate (0 = never)."""
    stop_confirm_episodes: int = 0
    """Before stopping early, fly this many more evaluation episodes (the seeds that follow) and
    stop only if all of them together still reach stop_on_success; that longer evaluation is the
    one recorded and compared for the best checkpoint (0 = stop on the periodic one alone)."""
    checkpoints_kept: int = 3
    """Checkpoints kept on disk; older ones are deleted (the newest good one is used on resume)."""
    replay_segment_rows: int = 50_000
    """Transitions per replay shard file on disk."""
    success_window: int = 100
    """Episodes in the rolling success rate of the progress bar and plots."""
    torch_threads: int = 1
    """CPU threads torch may use (keep 1 when several runs share a machine; rl/learner/torch_threads.py)."""
    device: str = "cpu"
    """Torch device: cpu, cuda or auto (cuda when present)."""
    ppo: dict = field(default_factory=dict)
    """Stable-Baselines3 PPO constructor arguments (algorithm ppo), e.g. `{n_steps: 256}`."""
    sac: dict = field(default_factory=dict)
    """Stable-Baselines3 SAC constructor arguments (algorithm sac), e.g. `{buffer_size: 100000}`."""
    td3: dict = field(default_factory=dict)
    """Stable-Baselines3 TD3 constructor arguments (algorithm td3)."""

    def __post_init__(self) -> None:
        if self.experiment in ALGORITHMS and self.experiment != self.algorithm:
            object.__setattr__(self, "experiment", self.algorithm)  # name the run after what trains
        self.validate()

    def unused_dqn_settings(self) -> list[str]:
        """DQN hyperparameters set away from their defaults in a config that trains an SB3
        algorithm (which reads only its own mapping): what a user may expect to apply and does not."""
        if self.algorithm == "dqn":
            return []
        defaults = TrainConfig()
        return [f.name for f in dataclasses.fields(self)
                if f.name not in RUN_WIDE and getattr(self, f.name) != getattr(defaults, f.name)]

    @property
    def sb3_arguments(self) -> dict[str, Any]:
        """The chosen SB3 algorithm's constructor arguments ({} for dqn)."""
        return dict(getattr(self, self.algorithm)) if self.algorithm in SB3_SECTIONS else {}

    def validate(self, source: str = "train") -> None:
        """Raise ConfigError on values that cannot work (one line, naming the field)."""
        finite = all(math.isfinite(v) for v in dataclasses.astuple(self) if isinstance(v, float))
        if not finite:
            name = next(f.name for f in dataclasses.fields(self)
                        if isinstance(getattr(self, f.name), float) and not math.isfinite(getattr(self, f.name)))
            raise ConfigError(f"{source}: {name}: expected a finite number, got {getattr(self, name)!r}")
        checks: list[tuple[str, bool, str]] = [
            ("experiment", bool(SAFE_NAME.fullmatch(self.experiment)),
             "a name of letters, digits, '_', '-' and '.' (at most 64, not starting with '.'): it becomes "
             "part of the run directory's name"),
            ("episodes", 0 <= self.episodes <= MAX_EPISODES, f"an integer in [0, {MAX_EPISODES}]"),
            ("gamma", 0.0 <= self.gamma <= 1.0, "a number in [0, 1]"),
            ("epsilon_max", 0.0 <= self.epsilon_max <= 1.0, "a number in [0, 1]"),
            ("epsilon_min", 0.0 <= self.epsilon_min <= self.epsilon_max, "a number in [0, epsilon_max]"),
            ("epsilon_decay", self.epsilon_decay >= 0.0, "a non-negative number"),
            ("explore_repeat_max", 1 <= self.explore_repeat_max <= 1000 and (self.explore_repeat_max == 1
                                                                          or self.num_envs == 1),
             "an integer in [1, 1000] (above 1 only with num_envs 1)"),
            ("explore_repeat_exponent", 0.0 < self.explore_repeat_exponent <= 10.0, "a number in (0, 10]"),
            ("guided_explore_episodes", 0 <= self.guided_explore_episodes <= MAX_EPISODES
             and (self.guided_explore_episodes == 0 or self.num_envs == 1),
             f"an integer in [0, {MAX_EPISODES}] (above 0 only with num_envs 1)"),
            ("guided_explore_share", 0.0 <= self.guided_explore_share <= 1.0, "a number in [0, 1]"),
            ("transfer_epsilon_max", 0.0 <= self.transfer_epsilon_max <= 1.0, "a number in [0, 1]"),
            ("learning_rate", 0.0 < self.learning_rate <= 10.0, "a positive number (at most 10)"),
            ("learning_rate_end", 0.0 <= self.learning_rate_end <= 10.0, "a non-negative number (at most 10)"),
            ("optimizer", self.optimizer in OPTIMIZERS, f"one of {', '.join(OPTIMIZERS)}"),
            ("loss", self.loss in LOSSES, f"one of {', '.join(LOSSES)}"),
            ("batch_size", 1 <= self.batch_size <= 65536, "an integer in [1, 65536]"),
            ("learning_starts", 0 <= self.learning_starts <= MAX_REPLAY_ROWS, f"an integer in [0, {MAX_REPLAY_ROWS}]"),
            ("train_every", 1 <= self.train_every <= 100_000, "an integer in [1, 100000]"),
            ("gradient_steps", 1 <= self.gradient_steps <= 1000, "an integer in [1, 1000]"),
            ("num_envs", 1 <= self.num_envs <= 1024, "an integer in [1, 1024]"),
            ("target_update_period", 1 <= self.target_update_period <= 10_000_000, "an integer in [1, 10000000]"),
            ("target_update_unit", self.target_update_unit in TARGET_UPDATE_UNITS, "steps or episodes"),
            ("replay_capacity", self.batch_size <= self.replay_capacity <= MAX_REPLAY_ROWS,
             f"an integer in [batch_size, {MAX_REPLAY_ROWS}] (each row holds two observations)"),
            ("layers", 1 <= self.layers <= 32, "an integer in [1, 32]"),
            ("hidden_units", 1 <= self.hidden_units <= 8192, "an integer in [1, 8192]"),
            ("max_grad_norm", self.max_grad_norm >= 0.0, "a non-negative number"),
            ("n_step", 1 <= self.n_step <= 100, "an integer in [1, 100]"),
            ("per_alpha", 0.0 <= self.per_alpha <= 1.0, "a number in [0, 1]"),
            ("per_beta", 0.0 <= self.per_beta <= 1.0, "a number in [0, 1]"),
            ("per_epsilon", 0.0 < self.per_epsilon <= 1e3, "a number in (0, 1000]"),
            ("eval_episodes", 0 <= self.eval_episodes <= 100_000, "an integer in [0, 100000]"),
            ("eval_every", 0 <= self.eval_every <= MAX_EPISODES, f"an integer in [0, {MAX_EPISODES}]"),
            ("stop_on_success", 0.0 <= self.stop_on_success <= 1.0, "a number in [0, 1]"),
            ("stop_confirm_episodes", 0 <= self.stop_confirm_episodes <= 100_000, "an integer in [0, 100000]"),
            ("checkpoints_kept", 2 <= self.checkpoints_kept <= 1000, "an integer in [2, 1000] (one to fall back on)"),
            ("replay_segment_rows", 1 <= self.replay_segment_rows <= MAX_REPLAY_ROWS, f"an integer in [1, {MAX_REPLAY_ROWS}]"),
            ("success_window", 1 <= self.success_window <= 1_000_000, "an integer in [1, 1000000]"),
            ("torch_threads", 1 <= self.torch_threads <= 1024, "an integer in [1, 1024]"),
            ("device", self.device in ("cpu", "cuda", "auto"), "cpu, cuda or auto"),
            ("algorithm", self.algorithm in ALGORITHMS, f"one of {', '.join(ALGORITHMS)}"),
        ]
        for name, ok, expected in checks:
            if not ok:
                raise ConfigError(f"{source}: {name}: expected {expected}, got {getattr(self, name)!r}")
        for name in SB3_SECTIONS:
            section = getattr(self, name)
            if not isinstance(section, dict):
                raise ConfigError(f"{source}: {name}: expected a mapping of {name.upper()} arguments, got {section!r}")
            if section or self.algorithm == name:
                check_arguments(name, section, f"{source}: {name}", needed=self.algorithm == name)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (YAML/JSON friendly), in field order."""
        return dataclasses.asdict(self)

    def replace(self, **changes: Any) -> TrainConfig:
        """A copy with some fields changed (validated)."""
        return dataclasses.replace(self, **changes)


@cache
def field_docs() -> dict[str, str]:
    """Field name -> its docstring, read from this class's source (the docs are the code)."""
    tree = ast.parse(inspect.getsource(TrainConfig))
    body = tree.body[0].body  # type: ignore[attr-defined]
    docs: dict[str, str] = {}
    for node, following in zip(body, body[1:], strict=False):
        if (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)
                and isinstance(following, ast.Expr) and isinstance(following.value, ast.Constant)
                and isinstance(following.value.value, str)):
            docs[node.target.id] = " ".join(following.value.value.split())
    return docs


def _field_types() -> dict[str, type]:
    defaults = TrainConfig()
    return {f.name: type(getattr(defaults, f.name)) for f in dataclasses.fields(TrainConfig)}


def parse_train_node(node: Node, base: TrainConfig | None = None) -> TrainConfig:
    """Read a `train:` mapping (missing keys keep `base`'s values); errors name file and key."""
    base = base or TrainConfig()
    if node.value is None:
        return base
    types = _field_types()
    node.reject_unknown(frozenset(types))
    changes: dict[str, Any] = {}
    for key, child in node.items():
        kind = types[key]
        if kind is bool:
            changes[key] = child.boolean()
        elif kind is int:
            changes[key] = child.integer()
        elif kind is float:
            changes[key] = child.number()
        elif kind is dict:
            changes[key] = dict(child.mapping()) if child.value is not None else {}
        else:
            changes[key] = child.string()
    try:
        return dataclasses.replace(base, **changes)
    except MissingExtra:
        raise
    except ConfigError as exc:
        # Re-point the message at the file and the `train.` key path.
        raise ConfigError(str(exc).replace("train: ", f"{node.source}: train.", 1)) from None


def load_train_config(world_path: str | Path, overrides: dict[str, Any] | None = None) -> TrainConfig:
    """The `train:` section of a scenario file (defaults where absent), then `overrides`."""
    root = load_yaml(world_file(world_path))
    config = parse_train_node(root.get("train", None) if isinstance(root.value, dict) else
                              Node(None, str(world_path), "train"))
    return apply_overrides(config, overrides or {})


def apply_overrides(config: TrainConfig, overrides: dict[str, Any]) -> TrainConfig:
    """`config` with the non-None entries of `overrides` (command-line values) applied."""
    changes = {k: v for k, v in overrides.items() if v is not None}
    try:
        return dataclasses.replace(config, **changes)
    except MissingExtra:
        raise  # names no key: nothing to re-point
    except ConfigError as exc:
        name, _, rest = str(exc).removeprefix("train: ").partition(": ")
        raise ConfigError(f"command line: --{name.replace('_', '-')}: {rest}") from None


def add_config_arguments(parser: argparse.ArgumentParser) -> None:
    """Add one `--field-name` option per TrainConfig field (help text = the field's docstring)."""
    group = parser.add_argument_group("hyperparameters (override the scenario's train: section)")
    docs = field_docs()
    defaults = TrainConfig()
    for name, kind in _field_types().items():
        if kind is dict:  # an algorithm's argument mapping: the scenario file's business
            continue
        flag = "--" + name.replace("_", "-")
        help_text = f"{docs.get(name, '')} [default {getattr(defaults, name)!r}]"
        if kind is bool:
            group.add_argument(flag, dest=f"cfg_{name}", action=argparse.BooleanOptionalAction,
                               default=None, help=help_text)
        else:
            group.add_argument(flag, dest=f"cfg_{name}", type=kind, default=None, metavar=kind.__name__.upper(),
                               help=help_text)


def overrides_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """The hyperparameters given on the command line (None where not given)."""
    return {name: getattr(args, f"cfg_{name}", None) for name, kind in _field_types().items() if kind is not dict}
