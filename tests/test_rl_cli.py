"""The RL commands end to end on the real scenario envs (`direct` backend, tiny runs): train,
resume, eval, plot, rules, lr-probe, curriculum with transfer, and the clear shape-mismatch error."""

from __future__ import annotations

import argparse
import importlib
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from sitl_bridge.rl.common.episode_log import read_records
from sitl_bridge.rl.learner.policy import policy_from_checkpoint

REPO = Path(__file__).resolve().parent.parent
EMPTY = str(REPO / "worlds" / "empty.yaml")          # 51 inputs
RANDOM_GOAL = str(REPO / "worlds" / "random_goal.yaml")  # 51 inputs: transfer from E works
WINDOW = str(REPO / "worlds" / "window.yaml")        # 65 inputs
TWO_DRONES = str(REPO / "worlds" / "two_drones_empty.yaml")
TINY = ["--batch-size", "16", "--layers", "2", "--hidden-units", "16", "--eval-every", "0",
        "--eval-episodes", "2", "--no-progress"]


def cli(*argv: str) -> int:
    """Run one of the RL subcommands through its own register()/func, as the CLI does."""
    parser = argparse.ArgumentParser()
    subparsers = parser.add_subparsers()
    for name in ("train", "eval", "lr_probe", "curriculum", "plot", "rules"):
        importlib.import_module(f"sitl_bridge.commands.{name}").register(subparsers)
    args = parser.parse_args(list(argv))
    return args.func(args)


def only_run(out: Path) -> Path:
    (run,) = [p for p in out.iterdir() if p.is_dir()]
    return run


@pytest.fixture(scope="module")
def empty_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("runs")
    assert cli("train", EMPTY, "--episodes", "2", "--seed", "3", "--out", str(out), *TINY) == 0
    return only_run(out)


def test_train_writes_a_complete_run_dir(empty_run: Path) -> None:
    assert empty_run.name.startswith("empty__e__3__")
    for name in ("run.json", "config.yaml", "episodes.jsonl", "eval.json", "replay/format.json"):
        assert (empty_run / name).is_file(), name
    assert list((empty_run / "checkpoints").glob("ckpt_0000002.safetensors"))
    assert list((empty_run / "tb").glob("events.out.tfevents.*"))
    records = read_records(empty_run / "episodes.jsonl")
    assert [r["episode"] for r in records] == [0, 1]
    first = records[0]
    assert first["outcome"] in ("goal", "crash", "out", "timeout")
    assert len(first["actions"]) == first["steps"] > 0
    assert first["sim_time_s"] == pytest.approx(first["steps"] * 1.0, abs=0.5)
    assert first["reward"] == pytest.approx(sum(first["reward_terms"].values()), abs=1e-6)
    # the CPU each episode and evaluation cost, for "minutes on one core" on a shared machine
    assert all(r["cpu_time_s"] > 0 for r in records)
    assert json.loads((empty_run / "eval.json").read_text())["cpu_time_s"] > 0


def test_resume_extends_a_finished_run(empty_run: Path, tmp_path: Path) -> None:
    assert cli("train", "--resume", str(empty_run), "--episodes", "3", "--no-progress") == 0
    assert [r["episode"] for r in read_records(empty_run / "episodes.jsonl")] == [0, 1, 2]


def test_eval_json_and_policy_from_checkpoint(empty_run: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli("eval", str(empty_run), "--world", EMPTY, "--episodes", "2", "--json") == 0
    result = json.loads(capsys.readouterr().out)
    assert result["episodes"] == 2 and 0.0 <= result["success_rate"] <= 1.0
    assert result["success_rate"] + result["crash_rate"] + result["out_rate"] + result["timeout_rate"] == pytest.approx(1.0)
    policy = policy_from_checkpoint(empty_run)
    assert policy(np.zeros(51, dtype=np.float32)) in range(8)
    with pytest.raises(ValueError, match="51 observation values, got 5"):
        policy(np.zeros(5))


def test_plot_writes_a_png(empty_run: Path) -> None:
    assert cli("plot", str(empty_run)) == 0
    png = empty_run / "learning_curves.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_rules_summary_fields(empty_run: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli("rules", str(empty_run), "--world", EMPTY, "--episodes", "3", "--json") == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["episodes"] == 3
    assert sum(summary["action_share"].values()) == pytest.approx(1.0)
    assert summary["statements"] and summary["statements"][0].startswith(("mostly", "most often"))
    assert sum(n for _, n in summary["top_sequences"]) <= 3


def test_init_from_with_wrong_shapes_fails_clearly(empty_run: Path, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    code = cli("train", WINDOW, "--episodes", "1", "--out", str(tmp_path), "--init-from", str(empty_run), *TINY)
    assert code == 2
    err = capsys.readouterr().err
    assert "51 inputs" in err and "65 inputs" in err and "8 outputs" in err
    assert not list(tmp_path.iterdir())  # nothing half-created


def test_two_drone_scenario_trains_one_shared_network(tmp_path: Path) -> None:
    assert cli("train", TWO_DRONES, "--episodes", "1", "--out", str(tmp_path), *TINY) == 0
    records = read_records(only_run(tmp_path) / "episodes.jsonl")
    assert sorted(r["drone"] for r in records) == [0, 1]
    assert {r["episode"] for r in records} == {0}


def test_lr_probe_reports_a_rate(capsys: pytest.CaptureFixture[str]) -> None:
    code = cli("lr-probe", EMPTY, "--batches", "2", "--epochs", "8", "--rates", "10", "0.001",
               "--batch-size", "32", "--layers", "2", "--hidden-units", "16", "--json")
    result = json.loads(capsys.readouterr().out)
    assert code == 0 and result["transitions"] >= 64
    assert [t["learning_rate"] for t in result["trials"]] == [10.0, 0.001]
    assert result["trials"][0]["diverged"] and not result["trials"][1]["diverged"]
    assert result["safe_learning_rate"] == 0.001


def test_curriculum_transfers_and_reevaluates_earlier_stages(tmp_path: Path) -> None:
    overrides = "{episodes: 2, batch_size: 16, layers: 2, hidden_units: 16, eval_every: 0, eval_episodes: 0}"
    file = tmp_path / "e_er.yaml"
    file.write_text(f"curriculum:\n  name: e_er\n  eval_episodes: 2\n  stages:\n"
                    f"    - world: {EMPTY}\n      train: {overrides}\n"
                    f"    - world: {RANDOM_GOAL}\n      train: {{transfer_epsilon_max: 0.5, {overrides[1:]}\n")
    assert cli("curriculum", str(file), "--out", str(tmp_path / "out"), "--no-progress") == 0
    state = json.loads((tmp_path / "out" / "e_er__0" / "curriculum.json").read_text())
    first, second = state["stages"]
    assert [e["world"] for e in first["evaluations"]] == [EMPTY]
    assert [e["world"] for e in second["evaluations"]] == [EMPTY, RANDOM_GOAL]
    run = json.loads((Path(second["run_dir"]) / "run.json").read_text())
    assert run["init_from"] == first["run_dir"]
    assert read_records(Path(second["run_dir"]) / "episodes.jsonl")[0]["epsilon"] == 0.5
    # Running it again resumes: nothing is retrained.
    assert cli("curriculum", str(file), "--out", str(tmp_path / "out"), "--no-progress") == 0
    assert json.loads((tmp_path / "out" / "e_er__0" / "curriculum.json").read_text()) == state


def short_scenario(tmp_path: Path, max_steps: int = 6) -> str:
    """worlds/empty.yaml with a shorter episode (scenarios are data: no code change)."""
    text = Path(EMPTY).read_text().replace("max_steps: 20", f"max_steps: {max_steps}", 1)
    assert f"max_steps: {max_steps}" in text
    path = tmp_path / "short_empty.yaml"
    path.write_text(text)
    return str(path)


def sigkill_training_midway(args: list[str], out: Path, pause_s: Callable[[list[dict]], float]) -> None:
    """Run `sitl-bridge <args> --out out` in a child process, wait until two episode records are
    logged, let it fly on for `pause_s(records)` wall seconds, then SIGKILL it (no clean-up)."""
    import signal
    import subprocess
    import sys
    import time

    code = "import sys; from tests.test_rl_cli import cli; sys.exit(cli(*sys.argv[1:]))"
    proc = subprocess.Popen([sys.executable, "-c", code, *args, "--out", str(out)], cwd=REPO,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline and proc.poll() is None:
            runs = list(out.glob("*/episodes.jsonl")) if out.exists() else []
            if runs and runs[0].read_text().count("\n") >= 2:
                break
            time.sleep(0.02)
        time.sleep(pause_s(read_records(runs[0])))
        assert proc.poll() is None, "the run ended before it could be killed"
        proc.send_signal(signal.SIGKILL)
        assert proc.wait(timeout=30) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_real_env_run_killed_with_sigkill_resumes_exactly(tmp_path: Path) -> None:
    world = short_scenario(tmp_path)
    args = ["train", world, "--episodes", "6", *TINY[:-1], "--eval-episodes", "0", "--no-progress"]
    assert cli(*args, "--out", str(tmp_path / "ref")) == 0
    reference = read_records(only_run(tmp_path / "ref") / "episodes.jsonl")

    out = tmp_path / "killed"
    # Into the third episode: a random fraction of the time an episode has taken so far.
    sigkill_training_midway(args, out, lambda records: np.random.default_rng().uniform(0.2, 0.8)
                            * np.mean([r["wall_time_s"] for r in records]))
    run = only_run(out)
    assert cli("train", "--resume", str(run), "--no-progress") == 0
    records = read_records(run / "episodes.jsonl")
    assert [r["episode"] for r in records] == list(range(6))

    def same(r: dict) -> tuple:
        return r["episode"], r["actions"], r["reward"], r["outcome"], r["env_seed"], r["epsilon"], r["mean_loss"]

    assert [same(r) for r in records] == [same(r) for r in reference]
