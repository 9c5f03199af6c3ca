"""The named episode sets (rl/experiments/seeds.py) are disjoint, the report sections fly the
set named for their job, and `sitl-bridge eval` flies a held-out set by default and says which."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from sitl_bridge.cli import main as cli
from sitl_bridge.rl.evaluation.rollout import eval_seeds
from sitl_bridge.rl.experiments import rules_section
from sitl_bridge.rl.experiments.seeds import (
    CHOOSE_SEED_BASE,
    EVAL_SEED_BASE,
    MINE_SEED_BASE,
    SEED_BASES,
    VERIFY_SEED_BASE,
    disjoint_seed_sets,
    seed_set,
)

REPO = Path(__file__).resolve().parent.parent
EMPTY = str(REPO / "worlds" / "empty.yaml")


def test_choosing_evaluation_mining_and_verification_sets_share_no_episode() -> None:
    assert len(set(SEED_BASES.values())) == 4
    # the report's sizes: 10 seeds, 100 evaluation episodes, and well beyond the 10/20 mined/verified
    assert disjoint_seed_sets(list(range(10)), 300)
    mined = set(eval_seeds(MINE_SEED_BASE, 10))
    verified = set(eval_seeds(VERIFY_SEED_BASE, 200))
    chose = {s for seed in range(10) for s in eval_seeds(seed_set(CHOOSE_SEED_BASE, seed), 40)}
    assert not mined & verified and not chose & (mined | verified)
    # the overlap the sets replace: verification used to extend the mining episodes
    assert set(eval_seeds(EVAL_SEED_BASE, 10)) <= set(eval_seeds(EVAL_SEED_BASE, 20))


def test_a_run_seed_may_not_reach_into_the_next_set() -> None:
    with pytest.raises(ValueError, match="run seed"):
        seed_set(EVAL_SEED_BASE, 1_000_000)


def test_rules_are_mined_and_verified_on_their_own_sets(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """What `_analyse` passes to the behaviour analysis and to the verification flights."""
    seen: dict[str, int] = {}

    class Stop(Exception):
        pass

    class Mined:  # what the behaviour analysis hands on: a rules document
        document = {"name": "stand-in", "frame": "world", "rules": [{"text": "hover", "action": "hover"}]}

    def analyse_runs(run_dirs, *, episodes, seed):  # noqa: ANN001, ANN202 - stands in for the flights
        seen["mined"] = seed
        return Mined()

    def verify_rules(rules_file, others, *, episodes, seed):  # noqa: ANN001, ANN202
        seen["verified"] = seed
        raise Stop

    import sitl_bridge.rl.analysis.behaviour_runs as behaviour_runs
    import sitl_bridge.rl.analysis.rule_policy as rule_policy

    monkeypatch.setattr(behaviour_runs, "analyse_runs", analyse_runs)
    monkeypatch.setattr(rule_policy, "verify_rules", verify_rules)
    results = {"empty": {"world": EMPTY, "seeds": [{"seed": 0, "run_dir": "r0"}]}}
    with pytest.raises(Stop):
        rules_section._analyse("empty", results, tmp_path, [], rules_section.ReportSettings(), lambda _: None)
    assert seen == {"mined": MINE_SEED_BASE, "verified": VERIFY_SEED_BASE}

def test_eval_flies_the_run_s_held_out_set_by_default(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "runs"
    assert cli(["train", EMPTY, "--episodes", "2", "--seed", "3", "--out", str(out), "--batch-size", "16",
                "--layers", "2", "--hidden-units", "16", "--eval-every", "1", "--eval-episodes", "1",
                "--no-progress"]) == 0
    (run,) = [p for p in out.iterdir() if p.is_dir()]
    capsys.readouterr()
    assert cli(["eval", str(run), "--episodes", "2", "--json"]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["episode_seed"] == EVAL_SEED_BASE + 3
    assert f"eval_seeds({EVAL_SEED_BASE + 3}, 2)" in captured.err and "run seed 3" in captured.err
    assert cli(["eval", str(run), "--episodes", "1", "--seed", "5", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["episode_seed"] == 5


def test_eval_help_says_which_checkpoint_flies(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        cli(["eval", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "its best checkpoint (best.safetensors;" in text
