"""The `backends` section of an experiment's results.json (`SECTION_HOOKS`): transfer between
autopilot backends.

Per scenario with finished runs, the result policy (best checkpoint) of each of its first
`backend_seeds` seeds (0: all) flies `backend_episodes` greedy episodes on each of `BACKENDS`
(`rl.experiments.backend_transfer.fly_on_backend`, reset seeds `eval_seeds(EVAL_SEED_BASE + seed, n)`: the
same episodes on every backend, the first ones of the report's greedy evaluation of that seed).
A backend that cannot run here (px4 without `PX4_BIN`) or fails is reported as skipped with the
reason.

`results["backends"][stem][backend]`: `success_mean` and `collision_mean` (mean over seeds; every
seed flies as many episodes, so this is also the pooled rate), `success_ci95` and `collision_ci95`
(pooled Wilson 95 % intervals over all drone-episodes of the seeds: `ci`), `outcomes`,
`mean_steps_success` (successful drone-episodes), `mean_step_m` (distance flown per step),
`seeds` (per seed: `seed`, `success`, `collision`, `episodes`, `drone_episodes`,
`mean_steps_success`), and for every backend but `REFERENCE`: `same_actions` (drone-episodes that
flew the reference's very actions), `differs` (a rate more than 10 points from the reference's)
and `why` (a line from the episodes, when it differs). A skipped backend has `skipped` (why),
null rates and no seeds. Flights are cached per scenario and backend (`DIR/backends/`) per seed,
while that seed's checkpoint, the scenario and the settings are the same.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sitl_bridge.rl.experiments import report_cache
from sitl_bridge.rl.experiments.backend_transfer import (
    BackendFlight,
    differs,
    fly_on_backend,
    pooled,
    same_actions,
    summary,
    why_differ,
)
from sitl_bridge.rl.experiments.runner import RESERVED, ReportSettings
from sitl_bridge.rl.experiments.seeds import EVAL_SEED_BASE

log = logging.getLogger(__name__)

BACKENDS_DIR = "backends"
BACKENDS = ("direct", "stub", "px4")
"""The backends of the table, the reference first."""
REFERENCE = BACKENDS[0]
"""The backend the experiments train on: the others are compared with it."""
CI_METHOD = "pooled Wilson 95 % over all drone-episodes of the seeds"


def _px4_missing() -> str | None:
    import os

    from sitl_bridge.autopilot.px4.process import Px4Error, find_px4_bin

    if not os.environ.get("PX4_BIN"):
        return "PX4_BIN not set (no real PX4 SITL build)"
    try:
        find_px4_bin()
    except Px4Error as exc:
        return str(exc)
    return None


REQUIREMENTS: dict[str, Callable[[], str | None]] = {"px4": _px4_missing}
"""Per backend that needs something this machine may lack: why it cannot run (None: it can)."""


def chosen_seeds(seeds: list[dict[str, Any]], settings: ReportSettings) -> list[dict[str, Any]]:
    """The finished seeds the table flies: the lowest `backend_seeds` (0: all)."""
    ordered = sorted(seeds, key=lambda s: s["seed"])
    return ordered[:settings.backend_seeds] if settings.backend_seeds else ordered


def skipped(reason: str) -> dict[str, Any]:
    return {"skipped": reason, "success_mean": None, "success_ci95": None, "collision_mean": None,
            "collision_ci95": None, "seeds": []}


def _flights(stem: str, backend: str, seeds: list[dict[str, Any]], world: Path, out: Path,
             settings: ReportSettings, say: Callable[[str], None]) -> dict[int, BackendFlight]:
    """Each seed's flight on `backend`: cached ones while their checkpoint is the same, the rest flown."""
    from sitl_bridge.rl.learner.policy import policy_from_checkpoint

    key = report_cache.cache_key(backend=backend, world=report_cache.world_digest(world),
                                 episodes=settings.backend_episodes, episode_seed=EVAL_SEED_BASE)
    cache = out / BACKENDS_DIR / f"{stem}_{backend}.json"
    stored: dict[str, Any] = report_cache.load(cache, key) or {}
    kept: dict[str, Any] = {}
    flights: dict[int, BackendFlight] = {}
    for s in seeds:
        run_dir = out / s["run_dir"]
        digest = report_cache.checkpoint_digest(run_dir)
        entry = stored.get(str(s["seed"]))
        if entry is None or entry["checkpoint"] != digest:
            say(f"  {stem} seed {s['seed']} on {backend}: {settings.backend_episodes} greedy episodes")
            flight = fly_on_backend(policy_from_checkpoint(run_dir), world, backend,
                                    episodes=settings.backend_episodes, seed=EVAL_SEED_BASE + s["seed"])
            entry = {"checkpoint": digest, "flight": flight.to_dict()}
            kept[str(s["seed"])] = entry
            report_cache.store(cache, key, {**stored, **kept})  # an interrupted px4 table keeps what it flew
        kept[str(s["seed"])] = entry
        flights[s["seed"]] = BackendFlight.from_dict(entry["flight"])
    return flights


def _entry(flights: dict[int, BackendFlight]) -> dict[str, Any]:
    per_seed = []
    for seed, flight in flights.items():
        per_seed.append({"seed": seed, "success": flight.success, "collision": flight.collision,
                         "episodes": flight.episodes, "drone_episodes": flight.drone_episodes,
                         "mean_steps_success": flight.mean_steps_success})
    total = summary(pooled(list(flights.values())))
    n = len(per_seed)
    return {"success_mean": sum(s["success"] for s in per_seed) / n, "success_ci95": total["success_ci95"],
            "collision_mean": sum(s["collision"] for s in per_seed) / n, "collision_ci95": total["collision_ci95"],
            "ci": CI_METHOD, "drone_episodes": total["drone_episodes"], "outcomes": total["outcomes"],
            "mean_steps_success": total["mean_steps_success"], "mean_step_m": total["mean_step_m"],
            "seeds": per_seed}


def _compare(entry: dict[str, Any], flights: dict[int, BackendFlight],
             reference: dict[int, BackendFlight]) -> None:
    """`same_actions`, `differs` and `why` of a backend against the reference, on the seeds both flew."""
    common = [seed for seed in flights if seed in reference]
    if not common:
        return
    mine, theirs = pooled([flights[s] for s in common]), pooled([reference[s] for s in common])
    entry["same_actions"] = same_actions(theirs, mine)
    entry["differs"] = differs(summary(theirs), summary(mine))
    entry["why"] = why_differ(REFERENCE, theirs, mine) if entry["differs"] else None


def scenario_backends(stem: str, results: dict[str, Any], out: Path, settings: ReportSettings,
                      say: Callable[[str], None]) -> dict[str, Any]:
    """Every backend's entry for one scenario (skipped ones with the reason)."""
    seeds = chosen_seeds(results[stem]["seeds"], settings)
    if not seeds:
        return {backend: skipped("no finished runs") for backend in BACKENDS}
    world = Path(results[stem]["world"]).resolve()
    say(f"backends of {stem}: {len(seeds)} seeds x {settings.backend_episodes} greedy episodes on "
        f"{', '.join(BACKENDS)}")
    entries: dict[str, Any] = {}
    flown: dict[str, dict[int, BackendFlight]] = {}
    for backend in BACKENDS:
        reason = REQUIREMENTS.get(backend, lambda: None)()
        if reason:
            entries[backend] = skipped(reason)
            continue
        try:
            flown[backend] = _flights(stem, backend, seeds, world, out, settings, say)
        except (RuntimeError, OSError, ValueError) as exc:  # Px4Error, ConfigError, CheckpointError among them
            log.exception("%s on %s failed", stem, backend)
            entries[backend] = skipped(f"failed: {type(exc).__name__}: {exc}")
            continue
        entries[backend] = _entry(flown[backend])
    for backend, flights in flown.items():
        if backend != REFERENCE and REFERENCE in flown:
            _compare(entries[backend], flights, flown[REFERENCE])
    return entries


def add_results_section(results: dict[str, Any], out: str | Path, *, settings: ReportSettings | None = None,
                        say: Callable[[str], None] = print) -> None:
    """Set `results["backends"]`: per scenario, per backend, the greedy rates of its seeds' policies."""
    settings = settings or ReportSettings()
    out = Path(out)
    results["backends"] = {stem: scenario_backends(stem, results, out, settings, say)
                           for stem in results if stem not in RESERVED}
