"""Statistics across runs (seeds): mean with a Student-t 95 % interval, the Wilson interval of a
proportion, the Mann-Whitney U test with its rank-biserial effect size, and Holm-Bonferroni
adjusted p-values for a family of tests.

scipy is imported inside the functions that need it (`pip install 'sitl-bridge[analysis]'`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

Z95 = 1.959964
"""Standard normal quantile of a two-sided 95 % interval."""


def _scipy_stats():  # noqa: ANN202 - the module
    try:
        from scipy import stats
    except ImportError:
        raise ImportError("this needs scipy: pip install 'sitl-bridge[analysis]'") from None
    return stats


def wilson_interval(successes: int, trials: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval of a proportion (sound at 0 and n, unlike the normal one)."""
    if trials == 0:
        return 0.0, 1.0
    p = successes / trials
    denominator = 1 + z * z / trials
    centre = (p + z * z / (2 * trials)) / denominator
    half = z * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / denominator
    return max(0.0, centre - half), min(1.0, centre + half)


def mean_ci95(values: Sequence[float]) -> tuple[float, tuple[float, float] | None]:
    """Mean and the two-sided 95 % Student-t interval of the mean (t with n - 1 degrees of
    freedom times the standard error); the interval is None with fewer than two values."""
    n = len(values)
    if n == 0:
        raise ValueError("mean_ci95 of no values")
    mean = math.fsum(values) / n
    if n < 2:
        return mean, None
    sd = math.sqrt(math.fsum((v - mean) ** 2 for v in values) / (n - 1))
    half = float(_scipy_stats().t.ppf(0.975, n - 1)) * sd / math.sqrt(n)
    return mean, (mean - half, mean + half)


@dataclass(frozen=True)
class MannWhitney:
    """Two-sided Mann-Whitney U test of sample `a` against sample `b`."""

    u: float
    """U statistic of `a`: pairs (x from a, y from b) with x > y, ties counting one half."""
    p_value: float
    effect_size: float
    """Rank-biserial correlation 2 U / (n_a n_b) - 1 = P(a > b) - P(a < b), in [-1, 1]:
    negative when `a` tends to be smaller than `b`."""
    n_a: int
    n_b: int


def mann_whitney(a: Sequence[float], b: Sequence[float]) -> MannWhitney:
    """Mann-Whitney U of `a` vs `b` (scipy's `mannwhitneyu`, two-sided: exact p without ties on
    small samples, else the normal approximation with tie correction) and the rank-biserial
    correlation. Identical samples (every value tied) give p = 1 and effect 0."""
    if not a or not b:
        raise ValueError("mann_whitney needs two non-empty samples")
    result = _scipy_stats().mannwhitneyu(list(a), list(b), alternative="two-sided")
    u = float(result.statistic)
    p = float(result.pvalue)
    if math.isnan(p):  # scipy's asymptotic test divides by a zero variance when all values tie
        p = 1.0
    return MannWhitney(u, p, 2.0 * u / (len(a) * len(b)) - 1.0, len(a), len(b))


def holm(p_values: Sequence[float | None]) -> list[float | None]:
    """Holm-Bonferroni adjusted p-values of a family of tests (None: a test not run, left out of
    the family): the k-th smallest of m is multiplied by m - k + 1, made non-decreasing in that
    order and capped at 1. An adjusted p below alpha rejects at family-wise error rate alpha."""
    ran = sorted((p, i) for i, p in enumerate(p_values) if p is not None)
    adjusted: list[float | None] = [None] * len(p_values)
    running = 0.0
    for k, (p, i) in enumerate(ran):
        running = max(running, min(1.0, (len(ran) - k) * p))
        adjusted[i] = running
    return adjusted
