"""A decision tree over observation features as a policy, as readable text and as a rules YAML.

The tree is kept in its own small structure (not scikit-learn's arrays) so that the policy that
is flown, the text a person reads and the rules file `eval --rules` flies are one and the same:
thresholds are rounded once, when the tree is built, and sibling leaves that pick the same action
are merged (a split that changes no decision is no rule).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from sitl_bridge.envs.features import FEATURE_MEANINGS
from sitl_bridge.rl.common.action_names import action_name

THRESHOLD_DECIMALS = 4
"""Thresholds are rounded to this many decimals (metres: a tenth of a millimetre)."""


@dataclass(frozen=True)
class Leaf:
    """Pick `action`; `samples` training states ended here."""

    action: int
    samples: int = 0


@dataclass(frozen=True)
class Split:
    """`low` when observation[feature] <= threshold, else `high`."""

    feature: int
    threshold: float
    low: Leaf | Split
    high: Leaf | Split


TreeNode = Leaf | Split


@dataclass(frozen=True)
class Condition:
    """observation[feature] `op` value, op `<=` or `>`."""

    feature: int
    op: str
    value: float

    def holds(self, obs: np.ndarray) -> bool:
        x = float(obs[self.feature])
        return x <= self.value if self.op == "<=" else x > self.value


def merge_equal_leaves(node: TreeNode) -> TreeNode:
    """`node` with every split whose two sides are leaves of the same action merged into one leaf."""
    if isinstance(node, Leaf):
        return node
    low, high = merge_equal_leaves(node.low), merge_equal_leaves(node.high)
    if isinstance(low, Leaf) and isinstance(high, Leaf) and low.action == high.action:
        return Leaf(low.action, low.samples + high.samples)
    return Split(node.feature, node.threshold, low, high)


@dataclass(frozen=True)
class TreePolicy:
    """A decision tree as a policy: `tree(obs) -> action code`."""

    root: TreeNode

    @classmethod
    def from_sklearn(cls, classifier: Any) -> TreePolicy:
        """The tree of a fitted `sklearn.tree.DecisionTreeClassifier` (classes = action codes)."""
        tree, classes = classifier.tree_, classifier.classes_

        def build(i: int) -> TreeNode:
            left, right = int(tree.children_left[i]), int(tree.children_right[i])
            if left == right:  # sklearn marks leaves with -1 on both sides
                return Leaf(int(classes[int(np.argmax(tree.value[i][0]))]), int(tree.n_node_samples[i]))
            return Split(int(tree.feature[i]), round(float(tree.threshold[i]), THRESHOLD_DECIMALS),
                         build(left), build(right))

        return cls(merge_equal_leaves(build(0)))

    def __call__(self, obs: np.ndarray) -> int:
        obs = np.asarray(obs).reshape(-1)
        node = self.root
        while isinstance(node, Split):
            node = node.low if obs[node.feature] <= node.threshold else node.high
        return node.action

    def predict(self, states: np.ndarray) -> np.ndarray:
        """Actions of a batch of observations (N, D)."""
        return np.array([self(s) for s in np.asarray(states)], dtype=np.int64)

    @property
    def depth(self) -> int:
        def depth(node: TreeNode) -> int:
            return 0 if isinstance(node, Leaf) else 1 + max(depth(node.low), depth(node.high))
        return depth(self.root)

    @property
    def leaves(self) -> int:
        return len(self.paths())

    def paths(self) -> list[tuple[list[Condition], Leaf]]:
        """Every leaf with the conditions on the way to it, tightest bound per feature and side
        only (`x <= 5 and x <= 3` is `x <= 3`); the leaves partition the observation space."""
        out: list[tuple[list[Condition], Leaf]] = []

        def walk(node: TreeNode, path: list[Condition]) -> None:
            if isinstance(node, Leaf):
                out.append((_tightest(path), node))
                return
            walk(node.low, path + [Condition(node.feature, "<=", node.threshold)])
            walk(node.high, path + [Condition(node.feature, ">", node.threshold)])

        walk(self.root, [])
        return out

    def used_features(self) -> list[int]:
        """Observation indices the tree splits on, ascending."""
        return sorted({c.feature for conditions, _ in self.paths() for c in conditions})


def _tightest(path: list[Condition]) -> list[Condition]:
    best: dict[tuple[int, str], Condition] = {}
    for c in path:
        key = (c.feature, c.op)
        old = best.get(key)
        if old is None or (c.value < old.value if c.op == "<=" else c.value > old.value):
            best[key] = c
    return sorted(best.values(), key=lambda c: (c.feature, c.op != ">"))


def feature_labels(layout: Mapping[str, slice], obs_dim: int) -> list[str]:
    """The name of every observation index: `NAME[INDEX]`, or `NAME` for a size-1 feature
    (the rules YAML's `feature` format); `x[i]` where the layout does not cover the vector."""
    labels = [f"x[{i}]" for i in range(obs_dim)]
    for name, block in layout.items():
        indices = range(obs_dim)[block]
        for offset, i in enumerate(indices):
            labels[i] = name if len(indices) == 1 else f"{name}[{offset}]"
    return labels


def _number(value: float) -> str:
    return f"{value:g}"


def _share(samples: int, total: int) -> str:
    share = samples / total
    return "<1%" if 0 < share < 0.005 else f"{share:.0%}"


def condition_text(condition: Condition, labels: list[str]) -> str:
    return f"{labels[condition.feature]} {condition.op} {_number(condition.value)}"


def tree_text(tree: TreePolicy, labels: list[str], frame: str = "world", words: Mapping[int, str] | None = None) -> str:
    """The tree as nested if-then text, actions named in `frame`, each leaf with its share of the
    training states, followed by what the features it uses mean and, for the indices `words`
    names (`features.index_words`: lidar rays), where each one points."""
    total = sum(leaf.samples for _, leaf in tree.paths()) or 1
    lines: list[str] = []

    def leaf_line(leaf: Leaf, indent: str, prefix: str) -> None:
        lines.append(f"{indent}{prefix}{action_name(leaf.action, frame)}   "
                     f"({_share(leaf.samples, total)} of states)")

    def walk(node: TreeNode, indent: str) -> None:
        if isinstance(node, Leaf):
            leaf_line(node, indent, "")
            return
        test = f"{labels[node.feature]} <= {_number(node.threshold)}"
        lines.append(f"{indent}if {test}:")
        walk(node.low, indent + "    ")
        lines.append(f"{indent}else:  # {labels[node.feature]} > {_number(node.threshold)}")
        walk(node.high, indent + "    ")

    if isinstance(tree.root, Leaf):
        leaf_line(tree.root, "", "always ")
    else:
        walk(tree.root, "")
    names = sorted({labels[i].split("[")[0] for i in tree.used_features()})
    if names:
        lines.append("where " + "; ".join(
            f"{n} = {FEATURE_MEANINGS[n][0]} [{FEATURE_MEANINGS[n][1]}]" if n in FEATURE_MEANINGS else n
            for n in names))
    pointing = [f"{labels[i]} {words[i]}" for i in tree.used_features() if words and i in words]
    if pointing:
        lines.append("rays: " + "; ".join(pointing))
    return "\n".join(lines)


def tree_rules(tree: TreePolicy, labels: list[str], *, frame: str, name: str, covers: list[str],
               source: str = "") -> dict[str, Any]:
    """The tree as a rules document (the rules YAML format): one rule per leaf, its path's
    conditions under `when`, the action by name in `frame`; the leaves partition the observation
    space, so exactly one rule holds for every observation and the order does not matter."""
    total = sum(leaf.samples for _, leaf in tree.paths()) or 1
    rules = []
    for conditions, leaf in tree.paths():
        action = action_name(leaf.action, frame)
        words = " and ".join(condition_text(c, labels) for c in conditions) or "always"
        rule: dict[str, Any] = {"text": f"{words}: {action} ({_share(leaf.samples, total)} of states)"}
        if conditions:
            rule["when"] = [{"feature": labels[c.feature], "op": c.op, "value": c.value} for c in conditions]
        rule["action"] = action
        rules.append(rule)
    document: dict[str, Any] = {"name": name, "covers": list(covers), "frame": frame}
    if source:
        document["source"] = source
    document["rules"] = rules
    return document
