"""The `algorithms` section of an experiment's results.json (`SECTION_HOOKS`): learning
algorithms and decision rates compared on the same scenarios and held-out episodes.

The experiment file puts scenarios in a row group with `group:` (e.g. DQN on the discrete table,
SAC and PPO on continuous velocity at 0.1 s and, through `action: {duration_s: 1.0}`, at 1 s);
each scenario is one row. Everything is read from the runs: the algorithm from each run's
`config.yaml`, the action type and decision period from its `scenario.yaml`, the learning time
from `evals.jsonl` and the episode log (the scenario's per-seed records, `results.learning_time`),
and the flights from the report's held-out greedy evaluation of each best checkpoint
(`held_out.GREEDY_FILE`, reset seeds `eval_seeds(EVAL_SEED_BASE + seed, n)`, never those of the
periodic evaluations that chose the checkpoint) with its per-episode flight measures
(`rl.evaluation.flight_measures`). It flies nothing itself.

`results["algorithms"][group]`: a list of rows, one per scenario of the group in the file's
order: `scenario`, `algorithm`, `action` (`discrete` or `velocity`), `decision_s`, `seeds`
(finished), `planned`, `drone_episodes`, `successes`, `success` (pooled over all held-out
drone-episodes of the seeds) with `success_ci95` (Wilson), `seed_success` (per seed: `seed`,
`success`), `seeds_90` (seeds whose held-out success is >= 90 %), `reached_90` (seeds whose
periodic evaluation reached 90 %), `episodes_to_90_median` and `wall_s_median` (median over
those), and over the successful held-out drone-episodes of all seeds: `goal_episodes` (those
with measures), `time_to_goal_s`, `path_m`, `command_change_m_s2` (means; null without any).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sitl_bridge.rl.experiments.held_out import EPISODE_MEASURES, THRESHOLD, held_out_record
from sitl_bridge.rl.experiments.runner import RESERVED, ReportSettings

MEASURES = ("time_s", "path_m", "command_change_m_s2")
"""Per-episode measures averaged over the successful held-out episodes, and their row keys."""
ROW_KEYS = {"time_s": "time_to_goal_s", "path_m": "path_m", "command_change_m_s2": "command_change_m_s2"}


def add_results_section(results: dict[str, Any], out: Path, *, settings: ReportSettings,
                        say: Callable[[str], None] = print) -> None:
    """Set `results["algorithms"]` (empty when no scenario has a `group:`)."""
    del settings, say  # nothing flown: the report's held-out evaluation already flew every episode
    groups: dict[str, list[str]] = {}
    for stem, entry in results.items():
        if stem not in RESERVED and isinstance(entry, dict) and entry.get("group") is not None:
            groups.setdefault(entry["group"], []).append(stem)
    results["algorithms"] = {group: [_row(stem, results[stem], Path(out)) for stem in stems]
                             for group, stems in groups.items()}


def _row(stem: str, entry: dict[str, Any], out: Path) -> dict[str, Any]:
    from sitl_bridge.rl.common.stats import wilson_interval

    seeds = entry["seeds"]
    row: dict[str, Any] = {"scenario": stem, "algorithm": None, "action": None, "decision_s": None,
                           "seeds": len(seeds), "planned": len(seeds) + len(entry.get("unfinished", []))}
    trials = successes = 0
    goals: list[dict[str, Any]] = []
    for record in seeds:
        run_dir = out / record["run_dir"]
        if row["algorithm"] is None:
            row.update(_run_kind(run_dir))
        held = held_out_record(run_dir) or {}
        episodes = held.get(EPISODE_MEASURES)
        if episodes is None:  # an evaluation cached before the measures: rates only
            count = int(held.get("result", {}).get("drone_episodes", 0))
            trials += count
            successes += round(record["greedy_success"] * count)
            continue
        trials += len(episodes)
        successes += sum(e["outcome"] == "goal" for e in episodes)
        goals += [e for e in episodes if e["outcome"] == "goal"]
    row.update({
        "drone_episodes": trials, "successes": successes,
        "success": successes / trials if trials else None,
        "success_ci95": list(wilson_interval(successes, trials)) if trials else None,
        "seed_success": [{"seed": s["seed"], "success": s["greedy_success"]} for s in seeds],
        "seeds_90": sum(s["greedy_success"] >= THRESHOLD for s in seeds),
        # the scenario table's own learning-time figures (`results.summarize_seeds`)
        "reached_90": entry["reached_90"],
        "episodes_to_90_median": entry["episodes_to_90_median"],
        "wall_s_median": entry["wall_s_median"],
        "goal_episodes": len(goals),
    })
    for measure in MEASURES:
        values = [e[measure] for e in goals if e.get(measure) is not None]
        row[ROW_KEYS[measure]] = math.fsum(values) / len(values) if values else None
    return row


def _run_kind(run_dir: Path) -> dict[str, Any]:
    """`algorithm` (config.yaml), `action` and `decision_s` (the run's own scenario copy)."""
    from sitl_bridge.envs.scenario import load_scenario
    from sitl_bridge.rl.training.run_dir import read_run_files, run_scenario

    _, config = read_run_files(run_dir)
    action = load_scenario(run_scenario(run_dir)).task.action
    return {"algorithm": config.algorithm, "action": "velocity" if action.continuous else "discrete",
            "decision_s": action.duration_s}
