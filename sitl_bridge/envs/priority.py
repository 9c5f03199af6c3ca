"""Who has right of way: an explicit priority per drone from a rule that could be applied in real
life, so a shared policy can learn "the lower priority yields" without leaning on the drone id
(the thesis's TW flaw: its id input created an unintended priority).

The scenario's `task.priority` names the rule:

| rule | priority (1 = right of way, 0 = yields) | real-life basis |
|---|---|---|
| `lower_coordinate_yields` (default) | ranked by start position: lower north, then lower east = lower | thesis rule 5 "the one with the lower GPS coordinates hovers" |
| `first_to_arrive` | ranked by remaining distance to the own goal, every step: nearer = higher | who arrives first goes first |

Ranks are scaled to [0, 1] (with one drone the priority is 1); ties break by the drone index.
"""

from __future__ import annotations

import numpy as np

PRIORITY_RULES = ("lower_coordinate_yields", "first_to_arrive")


def _ranks(keys: list[tuple[float, ...]]) -> np.ndarray:
    n = len(keys)
    if n == 1:
        return np.ones(1)
    order = sorted(range(n), key=lambda i: (*keys[i], i))
    ranks = np.empty(n)
    for rank, i in enumerate(order):
        ranks[i] = rank / (n - 1)
    return ranks


def priorities(rule: str, starts_enu_m: list[np.ndarray], positions_enu_m: list[np.ndarray],
               goals_enu_m: list[np.ndarray]) -> np.ndarray:
    """Priority in [0, 1] of every drone under `rule` (see the module table)."""
    if rule == "lower_coordinate_yields":
        return _ranks([(float(s[1]), float(s[0])) for s in starts_enu_m])
    if rule == "first_to_arrive":
        # Larger remaining distance ranks lower; rounded to cm so float noise cannot flip a tie.
        return _ranks([(-round(float(np.linalg.norm(g - p)), 2),)
                       for p, g in zip(positions_enu_m, goals_enu_m, strict=True)])
    raise ValueError(f"unknown priority rule {rule!r} (expected one of {', '.join(PRIORITY_RULES)})")
