"""Why a DQN seed collapses into crashing early: three measurements (docs/findings.md).

    python tools/collapse_probe.py mine RUN_DIR...
        From runs' episode logs (episodes.jsonl[.xz]): the episode of the first goal, and how
        episodes ended and how long they were, window by window. Cheap: trains nothing.
    python tools/collapse_probe.py returns SCENARIO.yaml [--gamma G]
        The discounted returns the scenario's reward terms give to "crash now", to "fly on to the
        step limit" (with and without bootstrapping at the limit) and to flying the path to the
        goal, from its reward config, gamma, step limit and the start's path distance to the goal (straight distance without a path term).
    python tools/collapse_probe.py explore SCENARIO.yaml --seeds 0,1 --episodes 300
        Pure exploration (uniformly random actions, the runs' own episode seeds): how many
        episodes reach the goal and the first that does.
    python tools/collapse_probe.py train SCENARIO.yaml --seed S --episodes N --every K --out DIR
        Trains a run as `sitl-bridge train` does (same trainer, same config) and every K episodes
        appends one JSON line to DIR/probe.jsonl: the online network's Q values at the start
        state (the action that crashes soonest when held, against the best other action), at the
        last state of the latest episode (the action taken, against the best other one), the
        replay's share of rows whose n-step window ends in a crash / goal / the step limit, the
        share of prioritized-replay sampling mass on crash rows, and the recent episodes'
        outcomes and lengths.

Run it from the worktree root with PYTHONPATH=. so it measures that code.
"""

from __future__ import annotations

import argparse
import json
import lzma
import sys
from collections import Counter
from dataclasses import asdict
from pathlib import Path

import numpy as np

WINDOWS = (0, 50, 100, 200, 300, 500, 800, 1100, 1500)


# -- mine -------------------------------------------------------------------------------------
def read_log(run_dir: Path) -> list[dict]:
    """The episode records of a run directory (plain or xz-compressed log)."""
    for name, opener in (("episodes.jsonl", open), ("episodes.jsonl.xz", lzma.open)):
        path = run_dir / name
        if path.is_file():
            with opener(path, "rt") as handle:
                return [json.loads(line) for line in handle if line.strip()]
    raise SystemExit(f"{run_dir}: no episodes.jsonl(.xz)")


def mine(run_dir: Path, early_steps: int = 11) -> dict:
    """First goal and per-window outcomes of one run's training episodes."""
    records = read_log(run_dir)
    goals = [r["episode"] for r in records if r["outcome"] == "goal"]
    first = goals[0] if goals else None
    windows = []
    for lo, hi in zip(WINDOWS, WINDOWS[1:], strict=False):
        chunk = [r for r in records if lo <= r["episode"] < hi]
        if not chunk:
            break
        outcomes = Counter(r["outcome"] for r in chunk)
        windows.append({"episodes": f"{lo}-{hi - 1}", "n": len(chunk),
                        **{k: outcomes.get(k, 0) for k in ("goal", "crash", "out", "timeout")},
                        "early_end": sum(r["outcome"] in ("crash", "out") and r["steps"] <= early_steps
                                         for r in chunk),
                        "mean_steps": round(float(np.mean([r["steps"] for r in chunk])), 1),
                        "epsilon_start": round(chunk[0]["epsilon"], 3)})
    return {"run": str(run_dir), "episodes": len(records), "first_goal_episode": first,
            "epsilon_at_first_goal": None if first is None else round(records[first]["epsilon"], 3),
            "steps_before_first_goal": None if first is None else records[first]["global_step"],
            "goals": len(goals), "windows": windows}


# -- returns ----------------------------------------------------------------------------------
def discounted(rewards: list[float], gamma: float) -> float:
    return float(sum(gamma ** k * r for k, r in enumerate(rewards)))


def reward_scales(scenario) -> dict[str, float]:
    return {term.name: term.scale for term in scenario.task.rewards}


def return_table(scenario, gamma: float, start_path_m: float, steps_to_crash: int) -> dict:
    """The returns of the ways an episode can go under `scenario`'s reward terms (1 m per step).

    crash_after_k: k - 1 steps, each gaining 1 m along the path, and the k-th a crash that gains
    nothing. fly_on: per_step every step, no progress (hovering, or a walk that ends where it
    began: the path shaping nets to zero), to the step limit; `truncation_cut` is the return
    when the limit is a real end, `bootstrapped` what a bootstrapping learner values flying on at
    when it believes no goal is ahead (per_step / (1 - gamma)). path_to_goal: the path's metres
    at 1 m per step, then the goal reward."""
    s = reward_scales(scenario)
    per_step, crash = s.get("per_step", 0.0), s.get("crash", 0.0)
    progress = s.get("closer_to_goal", 0.0)
    goal = s.get("goal_reached", 0.0)
    limit = scenario.task.max_steps
    crash_after = {k: discounted([per_step + progress] * (k - 1) + [per_step + crash], gamma)
                   for k in (1, steps_to_crash, 3)}
    steps_to_goal = int(np.ceil(start_path_m))
    to_goal = [per_step + progress] * steps_to_goal
    to_goal[-1] += goal
    fly_on_cut = discounted([per_step] * limit, gamma)
    fly_on_boot = per_step / (1.0 - gamma) if gamma < 1.0 else float("-inf")
    # The crash penalty at which crashing at once stops being cheaper than flying on to the limit.
    return {"gamma": gamma, "max_steps": limit, "rewards": s, "start_path_distance_m": round(start_path_m, 2),
            "crash_after_k_steps": {k: round(v, 1) for k, v in crash_after.items()},
            "fly_on_to_limit_truncation_cut": round(fly_on_cut, 1),
            "fly_on_bootstrapped": round(fly_on_boot, 1),
            "path_to_goal": round(discounted(to_goal, gamma), 1),
            "steps_to_goal": steps_to_goal,
            "crash_penalty_break_even_cut": round(fly_on_cut - per_step, 1),
            "crash_penalty_break_even_bootstrapped": round(fly_on_boot - per_step, 1)}


def start_facts(env, seed: int = 12345) -> tuple[float, list[dict]]:
    """The start's path distance to the goal and, per action held from the start, how the
    episode ends and after how many steps."""
    from sitl_bridge.rl.common.drones_env import episode_outcome

    _, infos = env.reset(seed)
    start = np.asarray(infos[0]["start_enu_m"], dtype=float)
    paths = getattr(env.env.runner, "_paths", [None])  # the runner's per-drone path fields
    # Without a path term, the straight distance (what the scenario's shaping pays along).
    path_m = (float(paths[0].distance(start)) if paths and paths[0] is not None
              else float(infos[0]["distance_to_goal_m"]))
    held = []
    for action in range(env.n_actions):
        env.reset(seed)
        steps, result = 0, None
        while env.live:
            result = env.step({0: action})
            steps += 1
        assert result is not None
        held.append({"action": action, "steps": steps,
                     "outcome": episode_outcome(result.infos[0], result.terminated[0], result.truncated[0])})
    return path_m, held


# -- explore ----------------------------------------------------------------------------------
def random_walk(scenario: str, seed: int, episodes: int, repeat_max: int = 1) -> dict:
    """Pure exploration: `episodes` episodes (the training run's episode seeds for `seed`) of
    uniformly random actions, each held for 1..`repeat_max` steps (uniform; 1: plain
    epsilon-greedy at epsilon 1). How often and how early it reaches the goal."""
    from sitl_bridge.rl.common.drones_env import DronesEnv, scenario_env_factory
    from sitl_bridge.rl.evaluation.rollout import episode_seed

    env = DronesEnv(scenario_env_factory(scenario, "direct")(seed))
    rng = np.random.default_rng(seed)
    outcomes: list[str] = []
    try:
        for episode in range(episodes):
            env.reset(episode_seed(seed, episode))
            action, left, result = 0, 0, None
            while env.live:
                if left == 0:
                    action, left = int(rng.integers(env.n_actions)), int(rng.integers(1, repeat_max + 1))
                result = env.step({0: action})
                left -= 1
            assert result is not None
            outcomes.append(str(result.infos[0].get("outcome")))
    finally:
        env.close()
    goals = [i for i, o in enumerate(outcomes) if o == "goal"]
    return {"scenario": scenario, "seed": seed, "episodes": episodes, "repeat_max": repeat_max,
            **Counter(outcomes), "first_goal_episode": goals[0] if goals else None}


# -- train ------------------------------------------------------------------------------------
def replay_shares(trainer, n_step: int, gamma: float) -> dict:
    """Shares of the replay's rows by how their n-step window ends (the row layout of
    rl/learner/nstep.py: `terminated` 1 after a real end; 1 - gamma^(m-1) for a window of m
    steps, so m < n marks a tail cut by the step limit), and the crash rows' share of the
    prioritized sampling mass."""
    replay = trainer.replay
    filled = len(replay)
    rows = replay.rows[:filled]
    term = rows["terminated"]
    real_end = term >= 1.0 - 1e-6
    goal = real_end & (rows["reward"] > 0)
    crash = real_end & ~goal
    full = 1.0 - gamma ** (n_step - 1)
    cut = ~real_end & (term < full - 1e-6)
    shares = {"rows": int(filled), "crash_or_out": round(float(crash.mean()), 4),
              "goal": round(float(goal.mean()), 4), "step_limit_tail": round(float(cut.mean()), 4)}
    if replay.priorities is not None and filled:
        mass = replay.priorities.values[:filled] ** replay.priorities.alpha
        shares["crash_sampling_mass"] = round(float(mass[crash].sum() / mass.sum()), 4)
    return shares


def q_report(q: np.ndarray, action: int) -> dict:
    others = np.delete(q, action)
    return {"q": [round(float(v), 1) for v in q], "action": action, "q_action": round(float(q[action]), 1),
            "best_other": round(float(others.max()), 1), "greedy": int(np.argmax(q))}


def probe(trainer, records: list[dict], crash_soonest: int, n_step: int, start_seed: int) -> dict:
    """One probe line (module docstring)."""
    from sitl_bridge.rl.evaluation.rollout import episode_seed

    obs, _ = trainer.env.reset(episode_seed(trainer.spec.seed, start_seed))
    start_q = trainer.agent.q_values(obs[0][None, :])[0]
    last = records[-1]
    rows = trainer.replay.rows[:len(trainer.replay)]
    # The latest episode's rows are the replay's last `steps` rows, one per step in order.
    mine_rows = rows[-last["steps"]:] if last["steps"] <= len(rows) else rows[:0]
    end = {}
    if len(mine_rows):
        q_last = trainer.agent.q_values(mine_rows["obs"][-1:])[0]
        end = {"outcome": last["outcome"], "steps": last["steps"], **q_report(q_last, int(mine_rows["action"][-1]))}
        q_all = trainer.agent.q_values(mine_rows["obs"])
        end["mean_max_q_along"] = round(float(q_all.max(axis=1).mean()), 1)
    recent = records[-trainer.config.eval_every:] if trainer.config.eval_every else records[-50:]
    outcomes = Counter(r["outcome"] for r in recent)
    return {"episode": trainer.episode, "global_step": trainer.global_step, "epsilon": round(trainer.epsilon(), 3),
            "start": q_report(start_q, crash_soonest), "last_episode_end": end,
            "replay": replay_shares(trainer, n_step, trainer.config.gamma),
            "recent": {"n": len(recent), **outcomes,
                       "mean_steps": round(float(np.mean([r["steps"] for r in recent])), 1)},
            "goals_so_far": sum(r["outcome"] == "goal" for r in records)}


def train(args: argparse.Namespace) -> None:
    from sitl_bridge.rl.common.drones_env import scenario_env_factory
    from sitl_bridge.rl.learner.config import load_train_config
    from sitl_bridge.rl.training.run_dir import RunSpec
    from sitl_bridge.rl.training.trainer import Trainer

    overrides = dict(json.loads(args.set)) if args.set else {}
    overrides["episodes"] = args.episodes
    config = load_train_config(args.scenario, overrides)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    spec = RunSpec(world=args.scenario, autopilot="direct", seed=args.seed)
    probe_file = out / "probe.jsonl"
    with Trainer.start(out / "runs", spec, config, scenario_env_factory(args.scenario, "direct"),
                       progress=False) as trainer:
        path_m, held = start_facts(trainer.env)
        soonest = min(held, key=lambda h: (h["outcome"] not in ("crash", "out"), h["steps"]))
        table = return_table(trainer.env.env.scenario, config.gamma, path_m, soonest["steps"])
        with probe_file.open("a") as handle:
            handle.write(json.dumps({"seed": args.seed, "config": config.to_dict(), "held_actions": held,
                                     "crash_soonest": soonest, "returns": table}) + "\n")
        records: list[dict] = []

        def on_episode(batch) -> None:
            records.extend(asdict(r) for r in batch)
            if trainer.episode % args.every == 0:
                line = probe(trainer, records, soonest["action"], config.n_step, 10**6)
                with probe_file.open("a") as handle:
                    handle.write(json.dumps(line) + "\n")
                print(json.dumps({k: line[k] for k in ("episode", "epsilon", "start", "recent", "goals_so_far")}),
                      flush=True)

        trainer.train(on_episode)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    m = sub.add_parser("mine")
    m.add_argument("run_dirs", nargs="+", type=Path)
    r = sub.add_parser("returns")
    r.add_argument("scenario")
    r.add_argument("--gamma", type=float, default=None)
    e = sub.add_parser("explore")
    e.add_argument("scenario")
    e.add_argument("--seeds", default="0")
    e.add_argument("--episodes", type=int, default=300)
    e.add_argument("--repeat-max", type=int, default=1)
    t = sub.add_parser("train")
    t.add_argument("scenario")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--episodes", type=int, default=400)
    t.add_argument("--every", type=int, default=25)
    t.add_argument("--out", required=True)
    t.add_argument("--set", default="", help='train overrides as JSON, e.g. \'{"n_step": 1}\'')
    args = parser.parse_args(argv)
    if args.command == "mine":
        for run_dir in args.run_dirs:
            print(json.dumps(mine(run_dir)))
    elif args.command == "returns":
        from sitl_bridge.rl.common.drones_env import DronesEnv, scenario_env_factory
        from sitl_bridge.rl.learner.config import load_train_config

        gamma = args.gamma if args.gamma is not None else load_train_config(args.scenario).gamma
        env = DronesEnv(scenario_env_factory(args.scenario, "direct")(0))
        try:
            path_m, held = start_facts(env)
            soonest = min(held, key=lambda h: (h["outcome"] not in ("crash", "out"), h["steps"]))
            print(json.dumps({"held_actions": held, "crash_soonest": soonest,
                              **return_table(env.env.scenario, gamma, path_m, soonest["steps"])}, indent=1))
        finally:
            env.close()
    elif args.command == "explore":
        for seed in map(int, args.seeds.split(",")):
            print(json.dumps(random_walk(args.scenario, seed, args.episodes, args.repeat_max)), flush=True)
    else:
        train(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
