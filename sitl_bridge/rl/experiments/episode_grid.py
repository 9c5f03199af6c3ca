"""A scenario's typical greedy episodes as one picture for RESULTS.md.

Every finished seed's best checkpoint flies `picture_episodes` greedy episodes
(`reflight.greedy_pictures`, reset seeds `eval_seeds(EVAL_SEED_BASE, n)`: the first episodes of
the behaviour analysis). The episodes are grouped by behaviour, each drone's manoeuvre and outcome
(`behaviour.classify_episode`), and the `picture_cells` most common groups are drawn, most common
first, each by its most common action sequence (`reflight.typical`), titled with how many of the
flown episodes it stands for and which seed and episode it is (`pictures.draw_grid`).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from sitl_bridge.rl.analysis.pictures import EpisodePicture

COLUMNS = 3


def behaviour_of(picture: EpisodePicture) -> str:
    """`pass_right+pass_right: goal+goal`: the episode's manoeuvres and outcomes, drones sorted."""
    from sitl_bridge.rl.analysis.behaviour import classify_episode

    episode = classify_episode(picture.traces, priority_rule=picture.scenario.task.priority)
    return f"{episode.pattern}: {'+'.join(sorted(d.outcome for d in episode.drones))}"


def _looks(picture: EpisodePicture) -> tuple:
    """What makes two pictures look the same: every drone's actions, start and goal (to 0.5 m)."""
    from sitl_bridge.rl.analysis.behaviour_summary import run_length

    def near(xyz: Any) -> tuple:
        return () if xyz is None else tuple(round(2 * float(v)) for v in xyz)

    return tuple((run_length(t.actions), near(t.positions_enu_m[0] if t.positions_enu_m else None),
                  near(t.goal_enu_m)) for t in picture.traces)


def _examples(members: list[EpisodePicture]) -> list[EpisodePicture]:
    """A behaviour's pictures to show, best first: its most common action sequence
    (`reflight.typical`), then the others in flight order, none that looks like one before it."""
    from sitl_bridge.rl.analysis.reflight import typical

    ((first, _),) = typical(members, 1)
    shown, seen = [first], {_looks(first)}
    for picture in members:
        if _looks(picture) not in seen:
            shown.append(picture)
            seen.add(_looks(picture))
    return shown


def typical_cells(flown: list[tuple[int, EpisodePicture]], cells: int) -> list[dict[str, Any]]:
    """Up to `cells` pictures of `flown` ((seed, picture) pairs): first one per behaviour, most
    common first (the earlier flown first among equals), each its behaviour's most common action
    sequence; cells left over show further episodes of the behaviours in the same order (other
    actions, starts or goals: a scenario with one behaviour still shows several episodes)."""
    groups: dict[str, list[tuple[int, EpisodePicture]]] = {}
    for seed, picture in flown:
        groups.setdefault(behaviour_of(picture), []).append((seed, picture))
    ranked = sorted(groups.items(), key=lambda kv: -len(kv[1]))  # stable: first flown first
    seed_of = {id(p): s for s, p in flown}
    examples = [_examples([p for _, p in members]) for _, members in ranked]
    chosen: list[dict[str, Any]] = []
    for rank in range(max((len(e) for e in examples), default=0)):
        for (behaviour, members), pictures in zip(ranked, examples, strict=True):
            if rank < len(pictures) and len(chosen) < cells:
                picture = pictures[rank]
                chosen.append({"behaviour": behaviour, "count": len(members), "seed": seed_of[id(picture)],
                               "episode": picture.traces[0].episode, "picture": picture})
    return chosen


def draw_typical_grid(runs: list[tuple[int, Path]], out: str | Path, *, episodes_per_seed: int, cells: int,
                      seed: int) -> dict[str, Any]:
    """Fly `episodes_per_seed` greedy episodes of every (training seed, run directory) of one
    scenario and draw the typical ones to `out` (.png). Returns what the grid shows (JSON-ready)."""
    from sitl_bridge.rl.analysis.pictures import draw_grid
    from sitl_bridge.rl.analysis.reflight import greedy_pictures

    flown = [(training_seed, picture) for training_seed, run_dir in runs
             for picture in greedy_pictures(run_dir, range(episodes_per_seed), seed=seed)]
    chosen = typical_cells(flown, cells)
    total = len(flown)
    titles = [f"{c['behaviour']}\n{c['count']} of {total} episodes (seed {c['seed']}, episode {c['episode']})"
              for c in chosen]
    draw_grid([c["picture"] for c in chosen], out, titles, columns=COLUMNS)
    return {"episodes": total, "seeds": len(runs), "episodes_per_seed": episodes_per_seed, "episode_seed": seed,
            "cells": [{k: v for k, v in c.items() if k != "picture"} for c in chosen]}


def scenario_grid(stem: str, scenario: dict[str, Any], out: str | Path, *, episodes_per_seed: int, cells: int,
                  seed: int, say: Callable[[str], None] = print) -> dict[str, Any]:
    """The grid of one scenario of results.json (its finished seeds) at `out/figures/<stem>_episodes.png`;
    redrawn only when a checkpoint or the settings changed (`<stem>_episodes.json` beside it).
    Returns the grid's description with `figure` (relative to `out`)."""
    from sitl_bridge.rl.analysis.behaviour import why_not_classified
    from sitl_bridge.rl.experiments import report_cache

    if why := why_not_classified(Path(scenario["world"]).resolve()):  # the grid groups episodes by behaviour
        raise ValueError(why)
    out = Path(out)
    figure = Path("figures") / f"{stem}_episodes.png"
    runs = [(int(s["seed"]), out / s["run_dir"]) for s in scenario["seeds"]]
    key = report_cache.cache_key(checkpoints={str(s): report_cache.checkpoint_digest(d) for s, d in runs},
                                 episodes_per_seed=episodes_per_seed, cells=cells, episode_seed=seed)
    cache = out / figure.with_suffix(".json")
    grid = report_cache.load(cache, key)
    if grid is None or not (out / figure).is_file():
        say(f"typical episodes of {stem}: {len(runs)} seeds x {episodes_per_seed} greedy episodes")
        (out / figure).parent.mkdir(parents=True, exist_ok=True)
        grid = {**draw_typical_grid(runs, out / figure, episodes_per_seed=episodes_per_seed, cells=cells, seed=seed),
                "figure": str(figure)}
        report_cache.store(cache, key, grid)
    return grid
