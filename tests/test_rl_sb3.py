"""Stable-Baselines3 algorithms through `sitl-bridge train --algorithm`: the DQN run directory,
kill -9 and --resume continuing exactly (real SIGKILLs of real `python -m sitl_bridge train`
processes), the argument checks, and policies that every post-training command reads."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_rl_kill_faults import _jsonl, assert_same_run, kill_and_resume

from sitl_bridge.errors import ConfigError
from sitl_bridge.rl.learner.config import TrainConfig, load_train_config

pytest.importorskip("stable_baselines3")

ROOT = Path(__file__).parent.parent
PPO_TINY = {"n_steps": 16, "batch_size": 8, "n_epochs": 2, "policy_kwargs": {"net_arch": [16, 16]}}
SAC_TINY = {"buffer_size": 70, "learning_starts": 20, "batch_size": 16, "train_freq": 4, "gradient_steps": 2,
            "policy_kwargs": {"net_arch": [16, 16]}}


def scenario(tmp_path: Path, world: str, train: dict, **task: object) -> Path:
    """A copy of a shipped world with this `train:` section (and `task:` changes)."""
    data = yaml.safe_load((ROOT / "worlds" / world).read_text())
    data["train"] = train
    data["task"].update(task)
    path = tmp_path / world
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def sitl_bridge(*argv: str, cwd: Path = ROOT, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sitl_bridge", *argv], cwd=cwd, capture_output=True, text=True,
                          timeout=timeout, env={**os.environ, "PYTHONPATH": str(ROOT)})


# -- the algorithm and its arguments ----------------------------------------------------------------
def test_algorithm_comes_from_the_train_section_and_the_command_line_wins(tmp_path: Path) -> None:
    world = scenario(tmp_path, "empty.yaml", {"algorithm": "ppo", "ppo": {"n_steps": 32}})
    config = load_train_config(world)
    assert (config.algorithm, config.sb3_arguments, config.experiment) == ("ppo", {"n_steps": 32}, "ppo")
    assert load_train_config(world, {"algorithm": "dqn"}).algorithm == "dqn"
    assert load_train_config(world, {"algorithm": "dqn"}).experiment == "dqn"
    # DQN's own keys do not reach an SB3 algorithm: the plan says which are set and unused
    from sitl_bridge.rl.training.train_plan import plan_lines

    lines = plan_lines(load_train_config(world, {"gamma": 0.995, "layers": 2}))
    assert "plan: ppo (Stable-Baselines3) with train.ppo = {'n_steps': 32} (SB3's defaults for the rest)" in lines
    assert any(line.endswith("set them under train.ppo): gamma, layers") for line in lines)


def test_an_unknown_sb3_argument_is_one_line_naming_the_key(tmp_path: Path) -> None:
    world = scenario(tmp_path, "empty.yaml", {"algorithm": "ppo", "ppo": {"n_stepz": 32}})
    with pytest.raises(ConfigError, match=r"empty.yaml: train\.ppo\.n_stepz: not a PPO argument \(known: .*n_steps"):
        load_train_config(world)
    with pytest.raises(ConfigError, match=r"train: sac\.seed: not settable here \(the run's --seed seeds it\)"):
        TrainConfig(algorithm="sac", sac={"seed": 3})
    with pytest.raises(ConfigError, match=r"sac\.policy_kwargs\.activation_fn: expected one of tanh"):
        TrainConfig(algorithm="sac", sac={"policy_kwargs": {"activation_fn": "nn.Tanh"}})
    result = sitl_bridge("train", "worlds/empty.yaml", "--algorithm", "sac", "--out", str(tmp_path / "runs"))
    assert result.returncode == 2
    assert result.stderr.strip().splitlines()[-1].startswith("error: train.sac: ")
    assert "SAC and TD3 need continuous actions" in result.stderr
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").iterdir())


def test_a_missing_stable_baselines3_names_the_extra(tmp_path: Path) -> None:
    blocker = tmp_path / "block"
    blocker.mkdir()
    (blocker / "stable_baselines3.py").write_text("raise ImportError('not installed here')\n")
    result = subprocess.run([sys.executable, "-m", "sitl_bridge", "train", "worlds/empty.yaml", "--algorithm", "ppo",
                             "--out", str(tmp_path / "runs")], cwd=ROOT, capture_output=True, text=True, timeout=120,
                            env={**os.environ, "PYTHONPATH": f"{blocker}{os.pathsep}{ROOT}"})
    assert result.returncode == 2
    assert result.stderr.strip() == ("error: Stable-Baselines3 is not installed; install the sb3 extra "
                                     "(pip install 'sitl-bridge[sb3]') to train with ppo")


# -- kill -9 and --resume ----------------------------------------------------------------------------
def _kill_and_resume(tmp_path: Path, world: Path, kill_after: int, args: list[str]) -> tuple[Path, Path]:
    return kill_and_resume(tmp_path, [str(world), "--seed", "5", *args], lambda beat: beat["episode"] >= kill_after)


def test_ppo_killed_9_mid_run_resumes_exactly(tmp_path: Path) -> None:
    ppo = {**PPO_TINY, "n_steps": 8, "batch_size": 4}
    world = scenario(tmp_path, "empty.yaml", {"algorithm": "ppo", "ppo": ppo, "experiment": "ppo"}, max_steps=8)
    run_dir, reference = _kill_and_resume(tmp_path, world, 2, ["--episodes", "5", "--eval-every", "2",
                                                               "--eval-episodes", "1"])
    records = _jsonl(run_dir / "episodes.jsonl")
    assert [r["episode"] for r in records] == list(range(5))
    assert records[-1]["global_step"] > 2 * ppo["n_steps"]  # PPO updated several times, across the kill
    assert any(r["mean_loss"] is not None for r in records)
    assert_same_run(run_dir, reference)  # same episodes (actions), evaluations, weights, optimizer, rollout


@pytest.mark.slow
def test_sac_killed_9_mid_run_resumes_exactly_with_the_same_replay(tmp_path: Path) -> None:
    world = scenario(tmp_path, "obstacle_continuous.yaml", {"algorithm": "sac", "sac": SAC_TINY},
                     max_time_s=3)
    run_dir, reference = _kill_and_resume(tmp_path, world, 3, ["--episodes", "6", "--eval-every", "3",
                                                               "--eval-episodes", "1"])
    assert_same_run(run_dir, reference)
    shards = sorted(p.name for p in (run_dir / "replay").glob("*.npz"))
    assert shards == sorted(p.name for p in (reference / "replay").glob("*.npz"))
    assert not shards[0].startswith("r000000000000_")  # the ring wrapped: the oldest shards were pruned
    for name in shards:
        with np.load(run_dir / "replay" / name) as mine, np.load(reference / "replay" / name) as theirs:
            assert all(np.array_equal(mine[k], theirs[k]) for k in theirs.files), name
    actions = [r["actions"][0] for r in _jsonl(run_dir / "episodes.jsonl")]
    assert all(isinstance(a, list) and len(a) == 3 for a in actions)  # continuous commands logged
    assert json.loads((run_dir / "run.json").read_text())["seed"] == 5


# -- every command after training -------------------------------------------------------------------
def cli(capsys: pytest.CaptureFixture, *argv: str, stdout_only: bool = False) -> str:
    from sitl_bridge.cli import main

    capsys.readouterr()  # what earlier calls printed is not this command's
    code = main(list(argv))
    out = capsys.readouterr()
    assert code == 0, out.err[-2000:]
    return out.out if stdout_only else out.out + out.err


def _tiny_run(out: Path, world: Path, seed: int) -> Path:
    from sitl_bridge.cli import main

    assert main(["train", str(world), "--seed", str(seed), "--episodes", "4", "--eval-every", "2",
                 "--eval-episodes", "2", "--out", str(out), "--no-progress"]) == 0
    (run,) = [p for p in out.iterdir() if p.name.endswith(f"__{seed}__" + p.name.split("__")[-1])]
    return run


@pytest.mark.slow  # about a minute: two runs, MAVSDK on the stub twice
def test_a_tiny_ppo_run_goes_through_every_command_after_training(tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture) -> None:
    from sitl_bridge.rl.learner.checkpoint import resolve_checkpoint
    from sitl_bridge.rl.learner.policy import policy_from_checkpoint

    world = scenario(tmp_path, "empty.yaml", {"algorithm": "ppo", "ppo": PPO_TINY, "experiment": "tiny"},
                     max_steps=8)
    runs = [_tiny_run(tmp_path / f"s{seed}", world, seed) for seed in (0, 1)]
    run = runs[0]
    for name in ("run.json", "scenario.yaml", "config.yaml", "episodes.jsonl", "evals.jsonl", "best.safetensors",
                 "baseline.json", "tb", "heartbeat.json"):
        assert (run / name).exists(), name
    assert yaml.safe_load((run / "config.yaml").read_text())["algorithm"] == "ppo"
    policy = policy_from_checkpoint(run)
    assert (policy.algorithm, policy.n_actions, policy.continuous) == ("ppo", 8, False)
    state = resolve_checkpoint(run)[2]
    assert state["network"]["algorithm"] == "ppo"

    evaluated = cli(capsys, "eval", str(run), "--episodes", "2", "--json", stdout_only=True)
    assert json.loads(evaluated)["episodes"] == 2
    cli(capsys, "plot", *map(str, runs), "--out", str(tmp_path / "curves.png"))
    assert (tmp_path / "curves.png").stat().st_size > 1000
    cli(capsys, "replay", str(run), "--episode", "1", "--greedy", "--out", str(tmp_path / "greedy.png"))
    cli(capsys, "replay", str(run), "--episode", "1", "--out", str(tmp_path / "logged.png"))
    assert (tmp_path / "greedy.png").is_file() and (tmp_path / "logged.png").is_file()
    exported = cli(capsys, "export", str(run))
    assert "verified" in exported
    flown = policy_from_checkpoint(run / "policy.safetensors")
    obs = np.linspace(-1, 1, policy.obs_dim, dtype=np.float32)
    assert flown(obs) == policy(obs)  # the export computes what the checkpoint computes
    through_mavsdk = cli(capsys, "run", str(world), "--policy", str(run), "--episodes", "1")
    assert "episode 0 drone 0:" in through_mavsdk
    transfer = cli(capsys, "transfer", str(run), "--episodes", "1")
    assert "stub:" in transfer
    cli(capsys, "rules", str(run), "--episodes", "1")
    cli(capsys, "train", str(world), "--init-from", str(run), "--episodes", "1", "--eval-episodes", "0",
        "--out", str(tmp_path / "transfer"), "--no-progress")
    (started,) = (tmp_path / "transfer").iterdir()
    assert json.loads((started / "run.json").read_text())["init_from"] == str(run)
    pytest.importorskip("imageio")
    cli(capsys, "eval", str(run), "--episodes", "1", "--video", str(tmp_path / "videos"))
    assert list((tmp_path / "videos").glob("*.mp4"))


# -- sweep and experiment ---------------------------------------------------------------------------
def test_sweep_trains_the_algorithm_it_is_given(tmp_path: Path) -> None:
    world = scenario(tmp_path, "empty.yaml", {"ppo": PPO_TINY}, max_steps=6)
    result = sitl_bridge("sweep", str(world), "--algorithm", "ppo", "--seeds", "0", "--episodes", "2",
                         "--eval-every", "0", "--eval-episodes", "0", "--out", str(tmp_path / "sweep"))
    assert result.returncode == 0, result.stderr[-2000:]
    (row,) = json.loads((tmp_path / "sweep" / "summary.json").read_text())
    assert row["status"] == "done" and row["episodes"] == 2
    assert yaml.safe_load((Path(row["run_dir"]) / "config.yaml").read_text())["algorithm"] == "ppo"


def test_an_experiment_lists_one_world_once_per_algorithm(tmp_path: Path) -> None:
    from sitl_bridge.rl.experiments.runner import load_experiment

    world = scenario(tmp_path, "empty.yaml", {"ppo": PPO_TINY})
    path = tmp_path / "compare.yaml"
    path.write_text(yaml.safe_dump({"experiment": {"name": "compare", "seeds": [0], "scenarios": [
        {"world": str(world), "train": {"episodes": 3}},
        {"world": str(world), "algorithm": "ppo", "train": {"episodes": 3}}]}}))
    experiment = load_experiment(path)
    assert [(s.stem, s.overrides) for s in experiment.scenarios] == [
        ("empty", {"episodes": 3}), ("empty_ppo", {"episodes": 3, "algorithm": "ppo"})]
    path.write_text(path.read_text().replace("algorithm: ppo", "algorithm: a2c"))
    with pytest.raises(ConfigError, match=r"algorithm: expected one of dqn, ppo, sac, td3, got 'a2c'"):
        load_experiment(path)


def test_a_continuous_policy_file_records_its_algorithm_and_flies_the_same_command(tmp_path: Path) -> None:
    import gymnasium as gym

    from sitl_bridge.rl.learner.policy import policy_from_checkpoint
    from sitl_bridge.rl.learner.policy_file import (
        POLICY_FILE,
        build_network,
        online_tensors,
        policy_bytes,
        probe_q_values,
    )
    from sitl_bridge.rl.learner.sb3_learner import SB3Learner

    for algorithm in ("sac", "td3", "ppo"):
        learner = SB3Learner(algorithm, 5, gym.spaces.Box(-1, 1, (3,), np.float32),
                             {"policy_kwargs": {"net_arch": [8]}}, seed=1)
        network = online_tensors(learner.state_tensors())
        shape = learner.shape.to_dict()
        data = policy_bytes(network, shape, episode=7, exported_from="test",
                            probe_q=probe_q_values(build_network(shape, network)))
        (tmp_path / POLICY_FILE).write_bytes(data)
        header = json.loads(data[8:8 + int.from_bytes(data[:8], "little")])
        assert header["__metadata__"]["algorithm"] == algorithm
        policy = policy_from_checkpoint(tmp_path / POLICY_FILE)
        obs = np.array([0.5, -1.0, 2.0, 0.0, 1.0], dtype=np.float32)
        assert (policy.algorithm, policy.continuous, policy.episode) == (algorithm, True, 7)
        command = policy(obs)
        assert command.shape == (3,) and np.all(np.abs(command) <= 1.0)
        assert np.array_equal(command, learner.greedy(obs))


def test_td3_stopped_and_resumed_in_process_ends_as_an_uninterrupted_run(tmp_path: Path) -> None:
    from sitl_bridge.rl.common.drones_env import scenario_env_factory
    from sitl_bridge.rl.training.run_dir import RunSpec
    from sitl_bridge.rl.training.runs import resume_run, start_run

    td3 = {"buffer_size": 40, "learning_starts": 10, "batch_size": 8, "policy_delay": 2,
           "action_noise": {"type": "normal", "sigma": 0.2}, "policy_kwargs": {"net_arch": [8]}}
    world = scenario(tmp_path, "obstacle_continuous.yaml", {"algorithm": "td3", "td3": td3, "episodes": 4,
                                                             "eval_every": 2, "eval_episodes": 1}, max_time_s=2)
    config = load_train_config(world)
    spec = RunSpec(world=str(world), seed=2)
    runs = {}
    for name, first_session in (("whole", 4), ("resumed", 2)):
        with start_run(tmp_path / name, spec, config, scenario_env_factory(world), progress=False) as trainer:
            trainer.train(on_episode=lambda _records, t=trainer, n=first_session: t.episode < n)
            runs[name] = trainer.run_dir
    with resume_run(runs["resumed"], progress=False) as trainer:
        assert trainer.episode == 2
        trainer.train()
        assert trainer.learner.updates > 0 and trainer.learner.model._n_updates > 1
    assert_same_run(runs["resumed"], runs["whole"])

