"""The `trees` section of an experiment's results.json (`SECTION_HOOKS`): per scenario, the
greedy network of its best seed (highest report success, the lowest seed among equals) distilled
into a decision tree of depth <= `distill_depth` (`rl.analysis.distill.distill_run`: VIPER-weighted,
DAgger-resampled, `distill_iterations` x `distill_episodes` episodes), then tree and network flown
on the same `distill_episodes` evaluation episodes (`eval_seeds(EVAL_SEED_BASE, n)`).

`results["trees"][stem]`: `depth`, `leaves`, `fidelity` (share of the network's actions the tree
repeats on the states the tree visits), `success` and `network_success` (same episodes), crash
rates, returns, `seed` and `run_dir` of the distilled run, `meets_target` (the issue's target:
depth <= 6, fidelity >= 95 %, success within 5 points of the network's), `text` (if-then) and the
files `DIR/trees/<stem>.txt` (the text) and `DIR/trees/<stem>.yaml` (the tree as a rules YAML that
`eval --rules` flies). One seed per scenario keeps the report step cheap; `sitl-bridge distill
RUN_DIR` distils any other. Scenarios without finished runs are `{"status": "not run"}`; results
are cached (`DIR/trees/<stem>.json`) while the checkpoint, scenario and settings are the same.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sitl_bridge.rl.analysis.behaviour import why_not_classified
from sitl_bridge.rl.experiments import report_cache
from sitl_bridge.rl.experiments.runner import RESERVED, ReportSettings
from sitl_bridge.rl.experiments.seeds import EVAL_SEED_BASE

log = logging.getLogger(__name__)

TREES_DIR = "trees"
TEXT_FORMAT = 2
"""Bumped when the tree's text changes (2: the rays it tests named by direction): a cached tree
is distilled again."""
TARGET_DEPTH = 6
TARGET_FIDELITY = 0.95
TARGET_SUCCESS_GAP = 0.05
"""The issue's target for a distilled tree: depth <= 6, fidelity >= 95 %, success at most 5
points below the network's."""


def best_seed(seeds: list[dict[str, Any]]) -> dict[str, Any]:
    """The seed whose run is distilled: highest greedy success, the lowest seed among equals."""
    return max(seeds, key=lambda s: (s["greedy_success"], -s["seed"]))


def meets_target(tree: dict[str, Any]) -> bool:
    return (tree["depth"] <= TARGET_DEPTH and tree["fidelity"] >= TARGET_FIDELITY
            and tree["success"] >= tree["network_success"] - TARGET_SUCCESS_GAP - 1e-9)


def _distill(stem: str, world: Path, seed: dict[str, Any], out: Path, settings: ReportSettings,
             say: Callable[[str], None]) -> dict[str, Any]:
    from sitl_bridge.rl.analysis.distill import distill_run
    from sitl_bridge.rl.analysis.rule_policy import cover_name
    from sitl_bridge.rl.common.atomic import atomic_write_text

    say(f"distilling {stem} seed {seed['seed']}: depth <= {settings.distill_depth}, "
        f"{settings.distill_iterations} iterations x {settings.distill_episodes} episodes")
    result = distill_run(out / seed["run_dir"], max_depth=settings.distill_depth,
                         iterations=settings.distill_iterations, episodes=settings.distill_episodes,
                         seed=EVAL_SEED_BASE)
    folder = out / TREES_DIR
    folder.mkdir(parents=True, exist_ok=True)
    text_file, rules_file = folder / f"{stem}.txt", folder / f"{stem}.yaml"
    atomic_write_text(text_file, f"# {stem}: distilled tree of seed {seed['seed']} ({seed['run_dir']})\n"
                                 f"# depth {result.depth}, {result.leaves} leaves, fidelity {result.fidelity:.1%}, "
                                 f"success {result.success:.0%} (network {result.network_success:.0%}) "
                                 f"over {result.episodes} episodes\n{result.text}\n")
    result.rules["covers"] = [cover_name(world, folder)]
    atomic_write_text(rules_file, result.rules_yaml())
    tree = {"status": "done", "seed": seed["seed"], "run_dir": seed["run_dir"],
            "max_depth": settings.distill_depth, "iterations": settings.distill_iterations,
            **{k: v for k, v in result.to_dict().items() if k not in ("world", "candidates")},
            "text_file": f"{TREES_DIR}/{text_file.name}", "rules_file": f"{TREES_DIR}/{rules_file.name}"}
    tree["meets_target"] = meets_target(tree)
    return tree


def _tree_entry(stem: str, results: dict[str, Any], out: Path, settings: ReportSettings,
                say: Callable[[str], None]) -> dict[str, Any]:
    seed = best_seed(results[stem]["seeds"])
    world = Path(results[stem]["world"]).resolve()
    key = report_cache.cache_key(
        checkpoint=report_cache.checkpoint_digest(out / seed["run_dir"]), seed=seed["seed"],
        world=report_cache.world_digest(world), depth=settings.distill_depth,
        iterations=settings.distill_iterations, episodes=settings.distill_episodes, episode_seed=EVAL_SEED_BASE,
        text=TEXT_FORMAT)
    cache = out / TREES_DIR / f"{stem}.json"
    tree = report_cache.load(cache, key)
    if tree is None or not all((out / tree[k]).is_file() for k in ("text_file", "rules_file")):
        tree = _distill(stem, world, seed, out, settings, say)
        report_cache.store(cache, key, tree)
    else:
        say(f"distilled tree of {stem}: unchanged run, from {cache}")
    return tree


def add_results_section(results: dict[str, Any], out: str | Path, *, settings: ReportSettings | None = None,
                        say: Callable[[str], None] = print) -> None:
    """Set `results["trees"]`: per scenario its best seed's distilled tree (or why there is none)."""
    import importlib.util

    from sitl_bridge.rl.analysis.distill import ANALYSIS_EXTRA

    if importlib.util.find_spec("sklearn") is None:  # the whole section, not each scenario, is missing
        raise RuntimeError(f"distillation needs scikit-learn: {ANALYSIS_EXTRA}")
    settings = settings or ReportSettings()
    out = Path(out)
    trees: dict[str, Any] = {}
    for stem in (key for key in results if key not in RESERVED):
        if not results[stem]["seeds"]:
            trees[stem] = {"status": "not run", "reason": "no finished runs"}
            continue
        if why := why_not_classified(Path(results[stem]["world"]).resolve()):
            trees[stem] = {"status": "skipped", "reason": why}
            continue
        try:
            trees[stem] = _tree_entry(stem, results, out, settings, say)
        except (ValueError, OSError, RuntimeError) as exc:  # ConfigError, CheckpointError, no scikit-learn
            log.exception("distillation of %s failed", stem)
            trees[stem] = {"status": "failed", "reason": f"{type(exc).__name__}: {exc}"}
    results["trees"] = trees
