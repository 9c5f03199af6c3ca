"""The `behaviour` and `rules` sections of an experiment's results.json (`SECTION_HOOKS`).

Per scenario with finished runs, the best checkpoint of every seed flies the same
`behaviour_episodes` greedy episodes (`rl.analysis.behaviour_runs.analyse_runs`, reset seeds
`eval_seeds(MINE_SEED_BASE, n)`: the mining episodes, neither those that chose the checkpoints nor
those the rules are verified on, see `seeds`). From them:

- `results["behaviour"][stem]`: the manoeuvre counts and split across seeds and per seed, the
  scenario's actions named in its own frame, the thesis's rules 0-5 checked (recovered / not /
  not applicable, with support), and the scenario's rules YAML with its verification;
- `results["rules"]`: every candidate rule of every scenario (`scenario`, `text`, `support_seeds`,
  `support_episodes`, ... and `verification`: per scenario the rules YAML it is part of was flown
  in, `success` and `collision_rate` beside `network_success`, the greedy success of the network
  trained in that scenario, from the report's evaluation). A candidate the YAML does not keep
  (a minority, a competitor, not expressible) has no verification of its own.

Verification (the thesis's loop): `DIR/rules/<stem>.yaml` flies `verify_episodes` episodes
(`rule_policy.verify_rules`, reset seeds `eval_seeds(VERIFY_SEED_BASE, n)`, none of the mining
episodes) in the scenario it came
from and in every simpler scenario of the experiment before it: the earlier stages of the
experiment's comparisons (curricula) and the thesis's order `SIMPLER_THAN` (E < ER < TE, O < OR,
W < TW), transitively. A scenario whose features the rules cannot read is reported as skipped.

Scenarios without finished runs are `{"status": "not run"}`; results are cached per scenario
(`DIR/rules/<stem>.json`) while the checkpoints, worlds and settings are the same.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sitl_bridge.rl.analysis.behaviour import why_not_classified
from sitl_bridge.rl.analysis.candidate_rules import ANALYSIS_VERSION
from sitl_bridge.rl.experiments import report_cache
from sitl_bridge.rl.experiments.runner import RESERVED, ReportSettings
from sitl_bridge.rl.experiments.seeds import MINE_SEED_BASE, VERIFY_SEED_BASE

log = logging.getLogger(__name__)

RULES_DIR = "rules"
SIMPLER_THAN: dict[str, tuple[str, ...]] = {
    "random_goal": ("empty",),            # ER after E
    "random_obstacle": ("obstacle",),     # OR after O
    "two_drones_empty": ("random_goal",),  # TE after ER
    "two_drones_empty_relative": ("random_goal",),
    "two_drones_window": ("window",),     # TW after W
    "two_drones_window_relative": ("window",),
}
"""The thesis's incremental order by scenario file stem: the scenarios each one came after."""
VERIFICATION_KEYS = ("covered", "success", "collision_rate", "out_rate", "timeout_rate", "episodes",
                     "drone_episodes", "rules_fired", "rules_left_out")


def scenario_stems(results: dict[str, Any]) -> list[str]:
    return [key for key in results if key not in RESERVED]


def simpler_scenarios(results: dict[str, Any]) -> dict[str, list[str]]:
    """Per scenario of `results`, the scenarios of `results` before it (transitively), in the
    results' order: from `SIMPLER_THAN` and the stages of the comparisons' curricula."""
    stems = scenario_stems(results)
    before: dict[str, set[str]] = {stem: set(SIMPLER_THAN.get(stem, ())) for stem in stems}
    for comparison in (results.get("transfer") or {}).values():
        stages = list(comparison.get("stages") or [])
        for k, stem in enumerate(stages):
            before.setdefault(stem, set()).update(stages[:k])
    closure: dict[str, list[str]] = {}
    for stem in stems:
        seen: set[str] = set()
        todo = list(before.get(stem, ()))
        while todo:
            other = todo.pop()
            if other not in seen and other != stem:
                seen.add(other)
                todo += before.get(other, ())
        closure[stem] = [s for s in stems if s in seen]
    return closure


def scenario_world(results: dict[str, Any], stem: str) -> Path:
    """The scenario file of `stem` (results' `world`: relative to the working directory or absolute)."""
    return Path(results[stem]["world"]).resolve()


def _analyse(stem: str, results: dict[str, Any], out: Path, simpler: list[str], settings: ReportSettings,
             say: Callable[[str], None]) -> dict[str, Any]:
    """Behaviour, candidate rules, thesis checks and the verified rules YAML of one scenario."""
    from sitl_bridge.rl.analysis.behaviour_runs import analyse_runs
    from sitl_bridge.rl.analysis.candidate_rules import write_rules_yaml
    from sitl_bridge.rl.analysis.rule_policy import cover_name, verify_rules

    seeds = results[stem]["seeds"]
    run_dirs = [out / s["run_dir"] for s in seeds]
    world = scenario_world(results, stem)
    say(f"behaviour and rules of {stem}: {len(run_dirs)} seeds x {settings.behaviour_episodes} greedy episodes")
    report = analyse_runs(run_dirs, episodes=settings.behaviour_episodes, seed=MINE_SEED_BASE)
    folder = out / RULES_DIR
    document = {**report.document, "covers": [cover_name(world, folder)]}
    rules_file = write_rules_yaml(folder / f"{stem}.yaml", document)
    others = [scenario_world(results, s) for s in simpler]
    say(f"  rules/{stem}.yaml flown {settings.verify_episodes} episodes in {', '.join([stem, *simpler])}")
    flown = verify_rules(rules_file, others, episodes=settings.verify_episodes, seed=VERIFY_SEED_BASE)
    verification = {key: ({"covered": v["covered"], "skipped": v["skipped"]} if "skipped" in v
                          else {k: v[k] for k in VERIFICATION_KEYS}) for key, v in flown.items()}
    behaviour = {
        "status": "done", **report.analysis.to_dict(),
        "seed_labels": [run.label for run in report.analysis.runs],
        "episodes_per_seed": settings.behaviour_episodes, "episode_seed": MINE_SEED_BASE,
        "verify_seed": VERIFY_SEED_BASE,
        "frame": report.summary.frame, "outcomes": report.summary.outcomes,
        "actions": report.summary.action_share, "top_sequences": report.summary.top_sequences,
        "thesis_rules": [c.to_dict() for c in report.checks],
        "rules_file": f"{RULES_DIR}/{rules_file.name}", "yaml_rules": [r["text"] for r in document["rules"]],
        "rules_fidelity": report.fidelity,
        "recorded_steps": report.steps, "verification": verification,
    }
    rules = [{"scenario": stem, **rule.to_dict(),
              "rules_file": behaviour["rules_file"] if rule.in_yaml else None,
              "verification": verification if rule.in_yaml else {}} for rule in report.rules]
    return {"behaviour": behaviour, "rules": rules}


def _with_network(entry: dict[str, Any], results: dict[str, Any]) -> dict[str, Any]:
    """Each verification scenario's learned policy beside the rules (fresh from `results`, not
    cached), and the verification on every rule the YAML keeps."""
    verification = entry["behaviour"].get("verification", {})
    for stem, check in verification.items():
        scenario = results.get(stem) if stem not in RESERVED else None
        check["network_success"] = scenario.get("success_mean") if isinstance(scenario, dict) else None
        check["network_collision"] = scenario.get("collision_mean") if isinstance(scenario, dict) else None
    for rule in entry["rules"]:
        rule["verification"] = verification if rule["in_yaml"] else {}
    return entry


def _scenario_entry(stem: str, results: dict[str, Any], out: Path, simpler: list[str], settings: ReportSettings,
                    say: Callable[[str], None]) -> dict[str, Any]:
    """One scenario's behaviour and rules: from the cache when the runs and settings are the same."""
    seeds = results[stem]["seeds"]
    key = report_cache.cache_key(
        checkpoints={str(s["seed"]): report_cache.checkpoint_digest(out / s["run_dir"]) for s in seeds},
        worlds={s: report_cache.world_digest(scenario_world(results, s)) for s in [stem, *simpler]},
        behaviour_episodes=settings.behaviour_episodes, verify_episodes=settings.verify_episodes,
        episode_seed=MINE_SEED_BASE, verify_seed=VERIFY_SEED_BASE, analysis=ANALYSIS_VERSION)
    cache = out / RULES_DIR / f"{stem}.json"
    entry = report_cache.load(cache, key)
    if entry is None or not (out / entry["behaviour"]["rules_file"]).is_file():
        entry = _analyse(stem, results, out, simpler, settings, say)
        report_cache.store(cache, key, entry)
    else:
        say(f"behaviour and rules of {stem}: unchanged runs, from {cache}")
    return _with_network(entry, results)


def add_results_section(results: dict[str, Any], out: str | Path, *, settings: ReportSettings | None = None,
                        say: Callable[[str], None] = print) -> None:
    """Set `results["behaviour"]` (per scenario) and `results["rules"]` (every candidate rule).
    A scenario whose analysis fails is reported as failed; the others still are analysed."""
    settings = settings or ReportSettings()
    out = Path(out)
    order = simpler_scenarios(results)
    behaviour: dict[str, Any] = {}
    rules: list[dict[str, Any]] = []
    for stem in scenario_stems(results):
        if not results[stem]["seeds"]:
            behaviour[stem] = {"status": "not run", "reason": "no finished runs"}
            continue
        if why := why_not_classified(scenario_world(results, stem)):
            behaviour[stem] = {"status": "skipped", "reason": why}
            continue
        try:
            entry = _scenario_entry(stem, results, out, order[stem], settings, say)
        except (ValueError, OSError, RuntimeError) as exc:  # ConfigError, CheckpointError among them
            log.exception("behaviour analysis of %s failed", stem)
            behaviour[stem] = {"status": "failed", "reason": f"{type(exc).__name__}: {exc}"}
            continue
        behaviour[stem] = entry["behaviour"]
        rules += entry["rules"]
    results["behaviour"] = behaviour
    results["rules"] = rules
