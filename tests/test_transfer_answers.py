"""The transfer rows of RESULTS.md: Holm-Bonferroni over every test of the comparisons, the
answer saying what the control arm shows, and where the transfer runs ended."""

from __future__ import annotations

import pytest

from sitl_bridge.rl.common.stats import holm
from sitl_bridge.rl.experiments.report import _transfer_section
from sitl_bridge.rl.experiments.results import adjust_transfer_tests


def test_holm_multiplies_by_the_tests_left_and_keeps_the_order() -> None:
    assert holm([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.03, 0.06, 0.06, 0.02])
    assert holm([0.5, None, 0.9]) == [pytest.approx(1.0), None, pytest.approx(1.0)]
    assert holm([]) == []


def arm(success: float, median: float | None) -> dict:
    return {"seeds": [{}] * 10, "success_mean": success, "success_ci95": [success - 0.01, min(1.0, success + 0.01)],
            "reached_90": 10, "episodes_to_90_median": median}


def comparison(p: float, effect: float, with_success: float, without_success: float, control_p: float | None) -> dict:
    entry = {"from": "random_goal_relative", "to": "two_drones_empty_relative", "stages": [],
             "test": "Mann-Whitney U", "with": arm(with_success, 150), "without": arm(without_success, 300),
             "u": 11.5, "p_value": p, "effect_size": effect}
    if control_p is not None:
        entry["control"] = {**arm(0.99, 175), "epsilon_max": 0.45,
                            "with_vs_control": {"u": 40.0, "p_value": control_p, "effect_size": -0.2}}
    return entry


def test_the_er_te_row_says_the_control_explains_it_and_counts_the_tests() -> None:
    transfer = {"er_te": comparison(0.0035, -0.77, 0.977, 0.9995, 0.586),
                "w_tw": comparison(0.121, -0.42, 0.98, 0.89, None)}
    adjust_transfer_tests(transfer)
    assert transfer["er_te"]["family_tests"] == 3
    assert transfer["er_te"]["p_holm"] == pytest.approx(3 * 0.0035)
    assert transfer["w_tw"]["p_holm"] == pytest.approx(2 * 0.121)
    assert transfer["er_te"]["control"]["with_vs_control"]["p_holm"] == pytest.approx(0.586)
    text = "\n".join(_transfer_section({"transfer": transfer}))
    assert "3 tests in all" in text and "Holm-Bonferroni" in text
    row = next(line for line in text.splitlines() if line.startswith("| er_te:"))
    assert "transfer needed fewer episodes (Holm p < 0.05)" in row
    assert "not the earlier network, explains the difference" in row
    assert "the transfer runs end worse (97.7 vs" in row
    w_tw = next(line for line in text.splitlines() if line.startswith("| w_tw:"))
    assert "no significant difference at 5 % (Holm p)" in w_tw and "control" not in w_tw


def test_each_seed_is_described_by_what_it_did() -> None:
    from sitl_bridge.rl.experiments.report import seed_story

    def seed(n: int, success: float, reached: int | None, last: float | None) -> dict:
        return {"seed": n, "greedy_success": success, "episodes_to_90": reached, "last_eval_success": last}

    # the thesis setup's TW: seed 0 never learned, seeds 1-2 had good episodes but never held 90 %
    assert seed_story([seed(0, 0.08, None, 0.05), seed(1, 0.30, None, 0.2), seed(2, 0.80, None, 0.5)]) == (
        "seed 0: never learned (8 %); seeds 1-2: partly learned, never 90 % (30, 80 %)")
    assert seed_story([seed(0, 1.0, 50, 1.0), seed(1, 0.9, 60, 0.5), seed(2, 1.0, 40, 0.95)]) == (
        "seeds 0, 2: learned, held 90 %; seed 1: learned, then fell (last evaluation) (50 %)")
