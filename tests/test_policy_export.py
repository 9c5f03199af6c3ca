"""Policy-only exports and slim runs on real tiny runs (`direct` backend): `sitl-bridge export`,
every network-reading command taking a policy file, `--init-from` a policy file, episode logs read
as `.xz`, and `tools/slim_results.py` verifying each replacement before it removes anything."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from sitl_bridge.cli import main as cli
from sitl_bridge.rl.analysis.reflight import logged_episode
from sitl_bridge.rl.common.episode_log import read_records
from sitl_bridge.rl.learner.checkpoint import CheckpointError, load_checkpoint, resolve_checkpoint
from sitl_bridge.rl.learner.policy_file import (
    PROBE_TENSOR,
    PolicyFileError,
    build_network,
    online_tensors,
    probe_observations,
    read_policy,
)

REPO = Path(__file__).resolve().parent.parent
EMPTY = str(REPO / "worlds" / "empty.yaml")
TINY = ["--batch-size", "16", "--layers", "2", "--hidden-units", "16", "--eval-every", "1",
        "--eval-episodes", "2", "--no-progress"]


def only_run(out: Path) -> Path:
    (run,) = [p for p in out.iterdir() if p.is_dir()]
    return run


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 3-episode run with a best checkpoint, checkpoints and replay (never modified: copy it)."""
    out = tmp_path_factory.mktemp("runs")
    assert cli(["train", EMPTY, "--episodes", "3", "--seed", "1", "--out", str(out), *TINY]) == 0
    run = only_run(out)
    assert (run / "best.safetensors").is_file() and (run / "replay").is_dir()
    return run


@pytest.fixture
def run(trained: Path, tmp_path: Path) -> Path:
    copy = tmp_path / trained.name
    shutil.copytree(trained, copy)
    return copy


def eval_json(target: Path, capsys: pytest.CaptureFixture[str], *extra: str) -> dict:
    capsys.readouterr()
    assert cli(["eval", str(target), "--episodes", "3", "--json", *extra]) == 0
    result = json.loads(capsys.readouterr().out)
    result.pop("world")  # the same scenario, named by the run's copy or by worlds/
    return result


def test_export_is_the_network_alone_and_flies_the_same(run: Path, capsys: pytest.CaptureFixture[str]) -> None:
    before = eval_json(run, capsys)
    assert cli(["export", str(run)]) == 0
    policy = run / "policy.safetensors"
    assert "verified" in capsys.readouterr().out
    best_tensors, best_state = load_checkpoint(run / "best.safetensors")
    tensors, state = read_policy(policy)
    assert state["policy_only"] and state["episode"] == best_state["episode"]
    assert set(tensors) == {k for k in best_tensors if k.startswith("online.")}  # no optimizer, target, rng
    assert policy.stat().st_size < (run / "best.safetensors").stat().st_size / 2
    probes = probe_observations(state["network"]["obs_dim"])
    with torch.no_grad():
        assert torch.equal(build_network(state["network"], online_tensors(tensors))(probes),
                           build_network(best_state["network"], online_tensors(best_tensors))(probes))
    assert eval_json(policy, capsys, "--world", EMPTY) == before


def test_a_damaged_policy_file_is_refused_in_one_line(run: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli(["export", str(run)]) == 0
    policy = run / "policy.safetensors"
    data = bytearray(policy.read_bytes())
    data[-5] ^= 0x40  # inside the last tensor's bytes
    policy.write_bytes(bytes(data))
    with pytest.raises(PolicyFileError, match="checksum mismatch"):
        read_policy(policy)
    capsys.readouterr()
    assert cli(["eval", str(policy), "--world", EMPTY, "--episodes", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert "checksum mismatch" in err and "\n" not in err


def test_a_policy_that_computes_other_q_values_is_refused(run: Path) -> None:
    """A file whose checksum is right but whose stored probe answers are not the network's."""
    import safetensors.torch

    from sitl_bridge.rl.learner.policy_file import policy_bytes

    ckpt_tensors, ckpt_state = load_checkpoint(run / "best.safetensors")
    network = online_tensors(ckpt_tensors)
    wrong = torch.zeros(len(probe_observations(1)), ckpt_state["network"]["n_actions"])
    (run / "wrong.safetensors").write_bytes(policy_bytes(network, ckpt_state["network"], episode=1,
                                                         exported_from="x", probe_q=wrong))
    assert PROBE_TENSOR in safetensors.torch.load((run / "wrong.safetensors").read_bytes())
    with pytest.raises(PolicyFileError, match="Q values on the probe observations differ"):
        read_policy(run / "wrong.safetensors")


def test_slim_removes_only_after_the_export_is_verified(run: Path, capsys: pytest.CaptureFixture[str]) -> None:
    before = eval_json(run, capsys)
    (run / "policy.safetensors").mkdir()  # the export cannot be written: nothing may go
    assert cli(["export", str(run), "--slim"]) == 2
    assert (run / "checkpoints").is_dir() and (run / "replay").is_dir() and (run / "best.safetensors").is_file()
    (run / "policy.safetensors").rmdir()
    assert cli(["export", str(run), "--slim"]) == 0
    assert sorted(p.name for p in run.iterdir() if p.suffix == ".safetensors") == ["policy.safetensors"]
    assert not (run / "checkpoints").exists() and not (run / "replay").exists()
    assert resolve_checkpoint(run)[0].name == "policy.safetensors"
    assert resolve_checkpoint(run, latest=True)[0].name == "policy.safetensors"
    assert eval_json(run, capsys) == before
    capsys.readouterr()
    assert cli(["rules", str(run), "--episodes", "2"]) == 0
    assert cli(["distill", str(run), "--episodes", "2", "--iterations", "1", "--json"]) == 0
    assert cli(["transfer", str(run / "policy.safetensors"), "--autopilots", "direct", "--episodes", "2"]) == 0
    assert cli(["replay", str(run), "--greedy", "--episode", "0", "--out", str(run / "g.png")]) == 0
    assert (run / "g.png").stat().st_size > 1000


def test_init_from_a_policy_file(run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli(["export", str(run)]) == 0
    out = tmp_path / "next"
    assert cli(["train", EMPTY, "--episodes", "1", "--out", str(out), "--init-from",
                str(run / "policy.safetensors"), *TINY]) == 0
    started = only_run(out)
    assert json.loads((started / "run.json").read_text())["init_from"] == str(run / "policy.safetensors")
    capsys.readouterr()
    refused = tmp_path / "refused"
    assert cli(["train", EMPTY, "--episodes", "1", "--out", str(refused), "--init-from",
                str(run / "policy.safetensors"), "--transfer-replay", *TINY]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: --transfer-replay:") and "policy file" in err and "\n" not in err
    assert not refused.exists() or not list(refused.iterdir())


def test_the_resolver_names_what_it_was_given(tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match="neither a checkpoint or policy file nor a run directory"):
        resolve_checkpoint(tmp_path / "missing")


def test_slim_results_verifies_then_replaces(run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    tree = tmp_path
    before_eval = eval_json(run, capsys)
    records = read_records(run / "episodes.jsonl")
    files = {str(p): p.read_bytes() for p in tree.rglob("*") if p.is_file()}
    tool = [sys.executable, str(REPO / "tools" / "slim_results.py"), str(tree)]
    measured = subprocess.run([*tool, "--measure"], capture_output=True, text=True, timeout=120)
    assert measured.returncode == 0, measured.stderr
    assert "would go from" in measured.stdout
    assert {str(p): p.read_bytes() for p in tree.rglob("*") if p.is_file()} == files  # nothing changed

    done = subprocess.run(tool, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert not (run / "episodes.jsonl").exists() and (run / "episodes.jsonl.xz").is_file()
    assert read_records(run / "episodes.jsonl") == records
    assert logged_episode(run, 1) == [r for r in records if r["episode"] == 1]
    assert read_policy(run / "best.safetensors")[1]["policy_only"]
    assert not (run / "checkpoints").exists() and not (run / "replay").exists()
    assert eval_json(run, capsys) == before_eval
    assert cli(["plot", str(run), "--out", str(tmp_path / "p.png")]) == 0
    assert cli(["replay", str(run), "--episode", "1", "--out", str(tmp_path / "r.png")]) == 0
    again = subprocess.run(tool, capture_output=True, text=True, timeout=120)  # idempotent
    assert again.returncode == 0 and "from 0 to 0 bytes" in again.stdout
