"""RESULTS.md and its figures, made from results.json (and experiment.json: how it was made).

Figures (`DIR/figures/`): per scenario the learning curves of its seeds (`plots.plot_runs`, mean
and 95 % band) and a grid of its typical greedy episodes (`episode_grid`, `<stem>_episodes.png`),
per comparison the transfer runs' curves and the greedy success with and without the earlier
network in one panel (`plots.plot_greedy_groups`). The behaviour, rules, trees and backend sections
come from `results.json`'s `behaviour`, `rules`, `trees` and `backends` (`rule_results`,
`distill_results`, `backend_results`).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from sitl_bridge.rl.experiments.results import THRESHOLD
from sitl_bridge.rl.experiments.runner import RESERVED, Experiment, ReportSettings
from sitl_bridge.rl.experiments.seeds import (
    EVAL_SEED_BASE,
    MINE_SEED_BASE,
    SEED_BASES,
    VERIFY_SEED_BASE,
)

FIGURES = "figures"
RESULTS_MD = "RESULTS.md"
RESULTS_JSON = "results.json"
META_JSON = "experiment.json"


def scenario_stems(results: dict[str, Any]) -> list[str]:
    """The scenario keys of results.json, in their order."""
    return [key for key in results if key not in RESERVED]


def write_figures(results: dict[str, Any], out: str | Path, say: Callable[[str], None] = print,
                  settings: ReportSettings | None = None) -> None:
    """Draw every figure the results have runs for; record each one's path (relative to `out`)
    in its scenario's or comparison's object as `figure` (and `figure_with_runs`), and each
    scenario's grid of typical episodes as `episodes_grid` (a grid that fails is reported, not raised)."""
    from sitl_bridge.rl.analysis.plots import NotARun, plot_greedy_groups, plot_runs
    from sitl_bridge.rl.experiments.episode_grid import scenario_grid
    from sitl_bridge.rl.learner.checkpoint import CheckpointError

    settings = settings or ReportSettings()
    out = Path(out)
    (out / FIGURES).mkdir(parents=True, exist_ok=True)

    def dirs(group: dict[str, Any]) -> list[Path]:
        return [out / s["run_dir"] for s in group["seeds"]]

    def draw(name: str, holder: dict[str, Any], field: str, make: Callable[[Path], Path]) -> None:
        path = out / FIGURES / f"{name}.png"
        try:
            make(path)
        except NotARun as exc:
            say(f"figure {path.name} not drawn: {exc}")
            return
        holder[field] = f"{FIGURES}/{path.name}"

    for stem in scenario_stems(results):
        if results[stem]["seeds"]:
            draw(stem, results[stem], "figure", lambda p, s=stem: plot_runs(dirs(results[s]), p))
            try:
                results[stem]["episodes_grid"] = scenario_grid(
                    stem, results[stem], out, episodes_per_seed=settings.picture_episodes,
                    cells=settings.picture_cells, seed=EVAL_SEED_BASE, say=say)
            except (ValueError, OSError, CheckpointError) as exc:  # ConfigError among them
                say(f"figure {stem}_episodes.png not drawn: {type(exc).__name__}: {exc}")
    for name, comparison in results.get("transfer", {}).items():
        with_dirs = dirs(comparison["with"])
        if with_dirs:
            draw(f"transfer_{name}_with_runs", comparison, "figure_with_runs", lambda p, d=with_dirs: plot_runs(d, p))
        groups = {f"with the {comparison['from']} network": with_dirs,
                  "without (trained from scratch)": dirs(comparison["without"])}
        if comparison.get("control"):
            control = comparison["control"]
            groups[f"control (from scratch, epsilon from {control['epsilon_max']:g})"] = dirs(control)
        if any(groups.values()):
            draw(f"transfer_{name}", comparison, "figure", lambda p, g=groups, c=comparison: plot_greedy_groups(
                g, p, f"{c['to']}: greedy success with vs without\nthe {c['from']} network (same seeds)"))


# -- formatting ----------------------------------------------------------------------------------
def _pct(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.0f} %"


def _ci(interval: list[float] | None) -> str:
    return "" if interval is None else f" [{100 * interval[0]:.0f}, {100 * interval[1]:.0f}]"


def _num(value: float | None, digits: int = 0) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _unit(value: float | None, digits: int, unit: str) -> str:
    return "-" if value is None else f"{value:.{digits}f} {unit}"


def _duration(seconds: float | None) -> str:
    if seconds is None:
        return "-"
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.1f} h"


def _p(value: float | None) -> str:
    return "-" if value is None else (f"{value:.3f}" if value >= 0.001 else f"{value:.1e}")


def _cell(text: str) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


# -- RESULTS.md ----------------------------------------------------------------------------------
def render(results: dict[str, Any], meta: dict[str, Any]) -> str:
    """The whole RESULTS.md."""
    lines = [f"# Results: experiment `{meta['name']}`", ""]
    lines += [
        "Every number on this page is in `results.json` beside it and is reproduced by",
        "",
        f"    {meta['command']}",
        "",
        f"(run from the repository root; {meta['file']} names the scenarios, seeds and budgets. The command "
        "resumes: it skips finished runs, resumes unfinished ones and only then rebuilds this page; "
        "`--report-only` rebuilds it from the runs alone.) "
        f"Written {meta['written']} by sitl-bridge {meta['version']}"
        + (f", commit `{meta['git_commit']}`" if meta.get("git_commit") else "") + ".",
        "",
        f"Seeds {meta['seeds_text']} per scenario{_own_seeds(meta)}; each finished run's best checkpoint flown greedily for "
        f"{meta['eval_episodes']} episodes on held-out seeds (definitions at the end).",
        "",
    ]
    lines += _scenario_table(results) + _thesis_table(results) + _algorithms_table(results, meta)
    lines += _figures(results) + _transfer_section(results)
    lines += _backends_section(results, meta)
    lines += _episodes_section(results) + _behaviour_section(results, meta) + _rules_section(results, meta)
    lines += _trees_section(results, meta)
    lines += _per_seed(results) + _definitions(meta)
    return "\n".join(lines) + "\n"


def _own_seeds(meta: dict[str, Any]) -> str:
    """` (two_drones_empty: 0, 1, 2)`: the scenarios with seeds of their own."""
    own = meta.get("scenario_seeds") or {}
    return f" ({'; '.join(f'`{k}`: {_seed_text(v)}' for k, v in own.items())})" if own else ""


def _seed_text(seeds: list[int]) -> str:
    contiguous = list(seeds) == list(range(seeds[0], seeds[-1] + 1))
    return f"{seeds[0]}-{seeds[-1]}" if contiguous and len(seeds) > 1 else ", ".join(map(str, seeds))


def _scenario_table(results: dict[str, Any]) -> list[str]:
    lines = ["## Scenarios", "",
             "| scenario | seeds done | greedy success, mean [95 % CI] | collision rate | reached 90 % "
             "| held 90 % to the end | episodes to 90 % (median) | wall time to 90 % (median) | thesis |",
             "|---|---|---|---|---|---|---|---|---|"]
    for stem in scenario_stems(results):
        r = results[stem]
        thesis = r.get("thesis") or {}
        done = len(r["seeds"])
        planned = done + len(r.get("unfinished", []))
        name = f"`{stem}`" + (f" ({thesis['shorthand']})" if thesis.get("shorthand") else "")
        if not done:
            lines.append(f"| {name} | 0/{planned} | not run | | | | | | {_cell(thesis.get('result', '-'))} |")
            continue
        lines.append(f"| {name} | {done}/{planned} | {_pct(r['success_mean'])}{_ci(r['success_ci95'])} "
                     f"| {_pct(r['collision_mean'])} | {r['reached_90']}/{done} | {r.get('held_90', 0)}/{r['reached_90']} "
                     f"| {_num(r['episodes_to_90_median'])} "
                     f"| {_duration(r['wall_s_median'])} | {_cell(thesis.get('result', '-'))} |")
    return lines + [""]


def _thesis_table(results: dict[str, Any]) -> list[str]:
    rows = [(stem, results[stem].get("thesis") or {}) for stem in scenario_stems(results)]
    if not any(t for _, t in rows):
        return []
    lines = ["What the thesis reported beside ours: it gives no success rates, only whether learning "
             "was stable, from one or two runs per scenario, and the behaviour it found (action codes, "
             "its Table 2). Its verdict is about its runs; the last column says what each of our seeds did "
             f"(learned: a periodic evaluation reached {100 * THRESHOLD:.0f} %; held: still there at the end; "
             f"never learned: its best checkpoint under {100 * NEVER_LEARNED:.0f} % greedy success).", "",
             "| scenario | thesis | result | runs | behaviour found | source | our seeds |",
             "|---|---|---|---|---|---|---|"]
    for stem, t in rows:
        lines.append(f"| `{stem}` | {_cell(t.get('shorthand', '-'))} | {_cell(t.get('result', 'not in the thesis'))} "
                     f"| {_cell(t.get('runs', '-'))} | {_cell(t.get('behaviour', '-'))} | {_cell(t.get('source', '-'))} "
                     f"| {_cell(seed_story(results[stem]['seeds']))} |")
    return lines + [""]


def _algorithms_table(results: dict[str, Any], meta: dict[str, Any]) -> list[str]:
    """Learning algorithms and decision rates side by side (`algorithms_section`); nothing when
    no scenario of the experiment has a `group:`."""
    groups = results.get("algorithms")
    if not groups:
        return []
    lines = ["## Learning algorithms and decision rates", "",
             f"Per scenario (group), each row one algorithm and action setting, the same held-out episodes: every finished "
             f"seed's best checkpoint flown greedily for {meta['eval_episodes']} episodes on reset seeds "
             f"`eval_seeds({EVAL_SEED_BASE} + seed, n)`, none of those that chose the checkpoint. Success: pooled over "
             "all held-out drone-episodes of the seeds, Wilson 95 % interval; per seed: lowest and highest. Seeds >= 90 %: "
             f"held-out success of at least {100 * THRESHOLD:.0f} %. Episodes and wall time to 90 %: when the periodic "
             "evaluation during training first reached it, median over the seeds that did (reached). Time to goal "
             "(simulated s), path (m) and command change (m/s per s of flight: the summed change of the commanded velocity "
             "between decisions over the flight time; 0 is one constant command) are means over the successful held-out "
             "drone-episodes of all seeds; the path joins the positions at the decisions, so at 1 s decisions it can "
             "cut a curve short.", "",
             "| group | scenario | algorithm | actions | decision | seeds | success [95 % CI] | per seed | seeds >= 90 % "
             "| reached 90 % | episodes to 90 % | wall time to 90 % | time to goal | path | command change |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for group, rows in groups.items():
        for r in rows:
            if not r["seeds"]:
                lines.append(f"| {_cell(group)} | `{r['scenario']}` | | | | 0/{r['planned']} | not run "
                             "| | | | | | | | |")
                continue
            spread = [s["success"] for s in r["seed_success"]]
            lines.append(
                f"| {_cell(group)} | `{r['scenario']}` | {r['algorithm']} | {r['action']} | {r['decision_s']:g} s "
                f"| {r['seeds']}/{r['planned']} | {_pct(r['success'])}{_ci(r['success_ci95'])} "
                f"| {_pct(min(spread))}-{_pct(max(spread))} | {r['seeds_90']}/{r['seeds']} | {r['reached_90']}/{r['seeds']} "
                f"| {_num(r['episodes_to_90_median'])} | {_duration(r['wall_s_median'])} "
                f"| {_unit(r['time_to_goal_s'], 1, 's')} | {_unit(r['path_m'], 2, 'm')} "
                f"| {_num(r['command_change_m_s2'], 2)} |")
    return lines + [""]


NEVER_LEARNED = 0.2
"""Greedy success of a seed's best checkpoint below which it is said never to have learned."""


def seed_story(seeds: list[dict[str, Any]]) -> str:
    """What each seed did, seeds with the same outcome together: `seed 0: never learned (8 %);
    seeds 1, 2: partly learned, never 90 % (30, 80 %)`."""
    groups: dict[str, list[tuple[int, str]]] = {}
    for s in seeds:
        last = s.get("last_eval_success")
        if s.get("episodes_to_90") is not None:
            if last is None or last >= THRESHOLD:
                kind, value = f"learned, held {100 * THRESHOLD:.0f} %", None
            else:
                kind, value = "learned, then fell (last evaluation)", last
        elif s["greedy_success"] < NEVER_LEARNED:
            kind, value = "never learned", s["greedy_success"]
        else:
            kind, value = f"partly learned, never {100 * THRESHOLD:.0f} %", s["greedy_success"]
        groups.setdefault(kind, []).append((s["seed"], "" if value is None else f"{100 * value:.0f}"))
    parts = []
    for kind, members in groups.items():
        numbers = [str(seed) for seed, _ in members]
        values = [v for _, v in members if v]
        label = f"seed {numbers[0]}" if len(numbers) == 1 else f"seeds {_seed_text([m[0] for m in members])}"
        parts.append(f"{label}: {kind}" + (f" ({', '.join(values)} %)" if values else ""))
    return "; ".join(parts) or "not run"


def _figures(results: dict[str, Any]) -> list[str]:
    from sitl_bridge.rl.analysis.plots import MIN_BAND_RUNS

    lines = ["## Learning curves", "",
             "Per scenario, every finished seed: greedy success during training, training outcomes, reward "
             f"per term, exploration and loss (mean across seeds; the 95 % band only where at least {MIN_BAND_RUNS} "
             "seeds are still training, so a band from two runs does not flatten the other lines).", ""]
    for stem in scenario_stems(results):
        figure = results[stem].get("figure")
        lines.append(f"- `{stem}`: " + (f"[{figure}]({figure})" if figure else "not run"))
    return lines + [""]


def _transfer_section(results: dict[str, Any]) -> list[str]:
    transfer = results.get("transfer") or {}
    lines = ["## Incremental complexity: with vs without the earlier network", ""]
    if not transfer:
        return lines + ["No comparisons in this experiment.", ""]
    lines += ["The same seeds trained in the harder scenario from scratch (without) and from the easier "
              "scenario's run of the same seed (with, `--init-from` its best checkpoint). Episodes count "
              "only the training in the harder scenario. Test: " + next(iter(transfer.values()))["test"]
              + "; effect size: rank-biserial correlation P(with > without) - P(with < without), negative "
              f"when the transfer runs needed fewer episodes. {_family_text(transfer)}", "",
              "| comparison | seeds with / without | success with | success without | reached 90 % with / without "
              "| episodes to 90 % median with / without | U | p | p (Holm) | effect size | answer | thesis |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, c in transfer.items():
        w, wo = c["with"], c["without"]
        lines.append(
            f"| {name}: `{c['from']}` -> `{c['to']}` | {len(w['seeds'])} / {len(wo['seeds'])} "
            f"| {_pct(w['success_mean'])}{_ci(w['success_ci95'])} | {_pct(wo['success_mean'])}{_ci(wo['success_ci95'])} "
            f"| {w['reached_90']} / {wo['reached_90']} | {_num(w['episodes_to_90_median'])} / "
            f"{_num(wo['episodes_to_90_median'])} | {_num(c['u'], 1)} | {_p(c['p_value'])} | {_p(c.get('p_holm'))} "
            f"| {_num(c['effect_size'], 2)} | {_transfer_answer(c)} | {_cell(_thesis_note(c.get('thesis') or {}))} |")
    lines.append("")
    controls = {name: c["control"] for name, c in transfer.items() if c.get("control")}
    if controls:
        lines += ["A transfer run starts exploring at its `transfer_epsilon_max`, a run from scratch at 1.0. The control "
                  "runs train from scratch starting at the transfer runs' epsilon, so with vs control isolates what "
                  "the earlier network gives:", "",
                  "| comparison | control epsilon start | seeds | success control | reached 90 % "
                  "| episodes to 90 % median with / control | U | p | p (Holm) | effect size | answer |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for name, k in controls.items():
            test = k["with_vs_control"]
            lines.append(f"| {name} | {k['epsilon_max']:g} | {len(k['seeds'])} "
                         f"| {_pct(k['success_mean'])}{_ci(k['success_ci95'])} | {k['reached_90']} "
                         f"| {_num(transfer[name]['with']['episodes_to_90_median'])} / {_num(k['episodes_to_90_median'])} "
                         f"| {_num(test['u'], 1)} | {_p(test['p_value'])} | {_p(test.get('p_holm'))} "
                         f"| {_num(test['effect_size'], 2)} "
                         f"| {_answer(test)} |")
        lines.append("")
    for name, c in transfer.items():
        figures = [f"[{c[k]}]({c[k]})" for k in ("figure", "figure_with_runs") if c.get(k)]
        lines.append(f"- {name}: " + (", ".join(figures) if figures else "no figure (no finished runs)"))
    return lines + [""]


def _backends_section(results: dict[str, Any], meta: dict[str, Any]) -> list[str]:
    from sitl_bridge.rl.experiments.backends_section import CI_METHOD, REFERENCE

    lines = ["## Transfer between autopilot backends", ""]
    backends = results.get("backends")
    if backends is None:
        return lines + _not_run("backends", meta)
    settings = meta.get("report") or {}
    count = settings.get("backend_seeds")
    seeds = f"the first {count} finished seeds" if count else "every finished seed"
    lines += [f"The result policy (best checkpoint) of {seeds} of each scenario (`backend_seeds`) flown greedily for "
              f"{settings.get('backend_episodes', '?')} episodes per seed on each autopilot backend, the same reset seeds "
              f"on every backend (`eval_seeds({EVAL_SEED_BASE} + seed, n)`; `sitl-bridge transfer` flies the same code). "
              f"Rates: mean over seeds, interval: {CI_METHOD}. Steps: mean steps of the successful drone-episodes; "
              "m/step: distance flown per step; same actions: drone-episodes that flew exactly the actions they flew "
              f"on `{REFERENCE}`. The px4 rows need `PX4_BIN` (a real PX4 SITL build) when the report is made.", "",
              "| scenario | backend | seeds | drone-episodes | success [95 % CI] | collision rate [95 % CI] "
              f"| steps (successful) | m/step | same actions as `{REFERENCE}` | outcomes |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    why: list[str] = []
    for stem, entry in backends.items():
        reasons = {b.get("skipped") for b in entry.values()}
        if len(reasons) == 1 and None not in reasons:  # e.g. no finished runs: one row, not one per backend
            lines.append(f"| `{stem}` | all | skipped: {_cell(reasons.pop())} | | | | | | | |")
            continue
        for backend, b in entry.items():
            if b.get("skipped"):
                lines.append(f"| `{stem}` | {backend} | skipped: {_cell(b['skipped'])} | | | | | | | |")
                continue
            same = b.get("same_actions")
            same_text = "-" if same is None else f"{same['identical']} / {same['compared']}"
            outcomes = ", ".join(f"{k} {v}" for k, v in b["outcomes"].items() if v)
            lines.append(f"| `{stem}` | {backend} | {len(b['seeds'])} | {b['drone_episodes']} "
                         f"| {_pct(b['success_mean'])}{_ci(b['success_ci95'])} "
                         f"| {_pct(b['collision_mean'])}{_ci(b['collision_ci95'])} | {_num(b['mean_steps_success'], 1)} "
                         f"| {_num(b['mean_step_m'], 2)} | {same_text} | {outcomes} |")
            if b.get("why"):
                why.append(f"- `{stem}` on {backend}: {_cell(b['why'])}.")
    lines.append("")
    if why:
        lines += [f"Why they differ (success or collision rate more than 10 points from `{REFERENCE}`), from the "
                  "episodes:", "", *why, ""]
    else:
        lines += [f"No backend's success or collision rate is more than 10 points from `{REFERENCE}`'s.", ""]
    return lines


def _thesis_note(thesis: dict[str, str]) -> str:
    if not thesis:
        return "-"
    text = thesis.get("result", "-") + (f" ({thesis['runs']} runs)" if thesis.get("runs") else "")
    return text + (f"; {thesis['source']}" if thesis.get("source") else "")


def _family_text(transfer: dict[str, Any]) -> str:
    """How many tests the answers are corrected for, and how."""
    family = next((c.get("family_tests") for c in transfer.values() if c.get("family_tests") is not None), None)
    if family is None:
        return "Answers at 5 % per test, uncorrected (no adjusted p in these results)."
    return (f"{family} tests in all (each comparison's with vs without, and with vs control where there is a "
            "control arm); p (Holm): Holm-Bonferroni adjusted over those tests, and the answers use it "
            "(5 % family-wise error).")


def _significant(c: dict[str, Any]) -> bool:
    p = c.get("p_holm", c["p_value"])
    return p is not None and p < 0.05


def _answer(c: dict[str, Any]) -> str:
    if c["p_value"] is None:
        return "not run"
    faster = "fewer" if c["effect_size"] < 0 else "more"
    adjusted = "Holm p" if c.get("p_holm") is not None else "p"
    if _significant(c):
        return f"transfer needed {faster} episodes ({adjusted} < 0.05)"
    return f"no significant difference at 5 % ({adjusted})"


def _transfer_answer(c: dict[str, Any]) -> str:
    """The with-vs-without answer, what the control arm shows about it, and where the runs ended."""
    text = _answer(c)
    control = c.get("control")
    if control and c["p_value"] is not None and control["with_vs_control"]["p_value"] is not None:
        test = control["with_vs_control"]
        if _significant(test):
            text += (f"; also against the control from scratch at the same starting epsilon "
                     f"({control['epsilon_max']:g}): the earlier network helps")
        else:
            text += (f"; but not against the control from scratch at the same starting epsilon "
                     f"({control['epsilon_max']:g}; {_answer(test)}): the lower starting exploration, "
                     "not the earlier network, explains the difference")
    ended_with, ended_without = c["with"]["success_mean"], c["without"]["success_mean"]
    if ended_with is not None and ended_without is not None and ended_with != ended_without:
        text += (f"; the transfer runs end {'worse' if ended_with < ended_without else 'better'} "
                 f"({100 * ended_with:.1f} vs {100 * ended_without:.1f} % greedy success)")
    return text


def _not_run(name: str, meta: dict[str, Any]) -> list[str]:
    reason = (meta.get("sections_not_run") or {}).get(name, "no results")
    return [f"Not run ({reason}).", ""]


def _status(entry: dict[str, Any] | None) -> str | None:
    """Why a section's entry for a scenario holds no numbers (None: it does)."""
    if entry is None:
        return "not run"
    if entry.get("status") == "done":
        return None
    reason = entry.get("reason")
    return f"{entry.get('status', 'not run')}" + (f" ({_cell(reason)})" if reason else "")


def _episodes_section(results: dict[str, Any]) -> list[str]:
    lines = ["## Typical greedy episodes", "",
             "Per scenario, the best checkpoint of every finished seed flies a few greedy episodes; they are "
             "grouped by behaviour (each drone's manoeuvre and outcome) and the most common groups are drawn, "
             "most common first: top view above side view, each drone's path with its action codes "
             "(`3x4`: four steps of action 3, named in the scenario's own frame under the grid).", ""]
    for stem in scenario_stems(results):
        grid = results[stem].get("episodes_grid")
        if not grid:
            lines += [f"- `{stem}`: not run" if not results[stem]["seeds"] else f"- `{stem}`: not drawn", ""]
            continue
        behaviours = {c["behaviour"]: c["count"] for c in grid["cells"]}  # in the grid's order, once each
        shown = ", ".join(f"{name} ({count})" for name, count in behaviours.items())
        lines += [f"**`{stem}`**: {grid['episodes']} episodes ({grid['episodes_per_seed']} per seed, "
                  f"{grid['seeds']} seeds), {len(grid['cells'])} drawn; behaviours (episodes): {shown}.", "", f"![{stem}: typical greedy episodes]({grid['figure']})", ""]
    return lines


def _top(shares: dict[str, float], count: int = 3) -> str:
    """The `count` largest shares, largest first."""
    ranked = sorted(shares.items(), key=lambda kv: (-kv[1], kv[0]))[:count]
    return ", ".join(f"{name} {_pct(share)}" for name, share in ranked) or "-"


def _behaviour_section(results: dict[str, Any], meta: dict[str, Any]) -> list[str]:
    lines = ["## Behaviour across seeds", ""]
    behaviour = results.get("behaviour")
    if behaviour is None:
        return lines + _not_run("rules", meta)
    settings = meta.get("report") or {}
    lines += [f"Every finished seed's best checkpoint flies the same {settings.get('behaviour_episodes', '?')} greedy "
              f"episodes (the mining episodes, reset seeds `eval_seeds({MINE_SEED_BASE}, n)`); each drone-episode is classified into one "
              "manoeuvre from its trajectory (`rl/analysis/behaviour.py`). The split counts the successful drone-episodes; "
              "competing manoeuvres are reported side by side, never chosen silently. Yields by priority: episodes "
              "whose hover/back-off yields follow the scenario's priority rule; through the opening: episodes whose "
              "drones went through the shared window in priority order (catches yields by a climb or a sidestep).",
              "",
              "| scenario | successful / all drone-episodes | split (successful) | majority per seed | per episode "
              "| yields by priority | actions (own frame) |", "|---|---|---|---|---|---|---|"]
    details: list[str] = []
    for stem, b in behaviour.items():
        why = _status(b)
        if why:
            lines.append(f"| `{stem}` | {why} | | | | | |")
            continue
        seeds = b["per_seed"]
        wins = sum(sum(r["success_counts"].values()) for r in seeds)
        total = sum(sum(r["counts"].values()) for r in seeds)
        head = f"mostly {b['dominant']}: " if b["dominant"] else ("split: " if b["split"] else "")
        majorities = sorted(b["seed_majorities"].items(), key=lambda kv: (-kv[1], kv[0]))
        majority = (", ".join(f"{k} in {v}" for k, v in majorities) + f" of {b['seeds']}"
                    if b["seed_majorities"] else "-")
        patterns = _top(b["patterns"]) if any("+" in k for k in b["patterns"]) else "-"
        yields = b["yield_priority"]
        yielded = f"{yields['follows']} of {yields['episodes_with_yield']}" if yields["episodes_with_yield"] else "-"
        order = b.get("passing_order") or {}
        if order.get("episodes_with_order"):
            yielded += f"; through the opening {order['follows']} of {order['episodes_with_order']}"
        lines.append(f"| `{stem}` | {wins} / {total} | {head}{_cell(b['split_text']) or 'no success'} "
                     f"| {_cell(majority)} | {_cell(patterns)} | {yielded} "
                     f"| {_cell(_top(b['actions']))} ({b['frame']}) |")
        details += [f"<details><summary>`{stem}` per seed</summary>", "",
                    "| seed | manoeuvres (all drone-episodes) | reached the goal | majority of the successes |",
                    "|---|---|---|---|"]
        for r in seeds:
            counts = ", ".join(f"{k} {v}" for k, v in sorted(r["counts"].items(), key=lambda kv: -kv[1]))
            details.append(f"| {r['label']} | {counts} | {r['outcomes'].get('goal', 0)} / {sum(r['outcomes'].values())} "
                           f"| {r['majority'] or '-'} |")
        details += ["", "</details>", ""]
    return lines + [""] + details


def _rules_section(results: dict[str, Any], meta: dict[str, Any]) -> list[str]:
    lines = ["## Rules", ""]
    rules, behaviour = results.get("rules"), results.get("behaviour")
    if rules is None or behaviour is None:
        return lines + _not_run("rules", meta)
    settings = meta.get("report") or {}
    lines += ["Candidate rules from the classified episodes: the situation at the start of each manoeuvre "
              "(a condition over the scenario's observation features: for an obstacle, the lidar ray that best tells "
              "the steps where the network flew the manoeuvre's action from the others), the action flown there "
              "and its support "
              "(seeds in which it shows in at least half of the successful episodes; successful episodes "
              "showing it). The rules kept *in the YAML* make the scenario's rules file (first matching rule "
              "wins; without a supported unconditional rule it ends with the default: fly toward the goal); it "
              f"is flown as a scripted policy ({settings.get('verify_episodes', '?')} episodes, `eval --rules`, on the "
              f"verification episodes `eval_seeds({VERIFY_SEED_BASE}, n)`, none of those it was mined on) "
              "in the scenario it came from and in the simpler ones before it, beside the greedy success of "
              "the network trained in each (the report's evaluation above).", ""]
    for stem, b in behaviour.items():
        if _status(b):
            lines += [f"### `{stem}`", "", f"{_status(b).capitalize()}.", ""]
            continue
        mine = [r for r in rules if r.get("scenario") == stem]
        fidelity = "" if b.get("rules_fidelity") is None else (
            f"; it picks the network's action at {_pct(b['rules_fidelity'])} of {b['recorded_steps']} recorded steps")
        kept = "; ".join(f"{k + 1}. {_cell(text)}" for k, text in enumerate(b.get("yaml_rules", [])))
        lines += [f"### `{stem}`", "", f"Rules file [{b['rules_file']}]({b['rules_file']}) ({kept}){fidelity}.", "",
                  "| rule | support: seeds | support: successful episodes | in the YAML | agrees with the network |",
                  "|---|---|---|---|---|"]
        for r in mine:
            note = f" ({_cell(r['note'])})" if r.get("note") else ""
            lines.append(f"| {_cell(r['text'])}{note} | {r['support_seeds']} of {r['seeds']} "
                         f"| {r['support_episodes']} of {r['episodes']} | {'yes' if r['in_yaml'] else 'no'} "
                         f"| {_pct(r.get('agreement'))} |")
        if not mine:
            lines.append("| none: no successful episode | | | | |")
        lines += ["", "| rules flown in | covered | rules: success | rules: collision rate | network trained there: "
                  "success | network: collision rate |", "|---|---|---|---|---|---|"]
        for where, v in b["verification"].items():
            if "skipped" in v:
                lines.append(f"| `{where}` | {'yes' if v['covered'] else 'no'} | not flown: {_cell(v['skipped'])} | | | |")
                continue
            left_out = v.get("rules_left_out") or []  # rules on features this scenario lacks
            scenario = f"`{where}`" + (f" (left out, not observed there: {_cell('; '.join(left_out))})"
                                       if left_out else "")
            lines.append(f"| {scenario} | {'yes' if v['covered'] else 'no'} | {_pct(v['success'])} "
                         f"| {_pct(v['collision_rate'])} | {_pct(v.get('network_success'))} "
                         f"| {_pct(v.get('network_collision'))} |")
        lines.append("")
    return lines + _thesis_rules(behaviour)


def _thesis_rules(behaviour: dict[str, Any]) -> list[str]:
    """The thesis's rules 0-5: per rule, every scenario where it could be judged."""
    verdicts: dict[int, list[str]] = {}
    names: dict[int, str] = {}
    for stem, b in behaviour.items():
        for check in ([] if _status(b) else b["thesis_rules"]):
            names[check["rule"]] = check["text"]
            if not check["applicable"]:
                continue
            if check["recovered"] is None:
                said = f"`{stem}`: no evidence (no {check['units']})"
            else:
                said = (f"`{stem}`: **{'recovered' if check['recovered'] else 'not recovered'}**, held in "
                        f"{check['support_seeds']} of {check['seeds']} seeds ({check['support_episodes']} of "
                        f"{check['episodes']} {check['units']} {check['evidence']})")
            verdicts.setdefault(check["rule"], []).append(said)
    if not names:
        return []
    lines = ["### The thesis's rules 0-5", "",
             "Checked on the same classified episodes; a rule is recovered in a scenario when it holds in more than "
             "half of its seeds. Scenarios where a rule does not apply are left out.", "",
             "| thesis rule | found here |", "|---|---|"]
    for rule in sorted(names):
        lines.append(f"| {rule}: {_cell(names[rule])} | {'; '.join(map(_cell, verdicts.get(rule, []))) or 'not applicable in any scenario run'} |")
    return lines + [""]


def _trees_section(results: dict[str, Any], meta: dict[str, Any]) -> list[str]:
    lines = ["## Distilled decision trees", ""]
    trees = results.get("trees")
    if trees is None:
        return lines + _not_run("trees", meta)
    settings = meta.get("report") or {}
    lines += [f"The greedy network of each scenario's best seed distilled into a decision tree of depth <= "
              f"{settings.get('distill_depth', '?')} (VIPER-weighted, DAgger-resampled, "
              f"{settings.get('distill_iterations', '?')} iterations of {settings.get('distill_episodes', '?')} "
              "episodes; `sitl-bridge distill`). Fidelity: share of the network's actions the tree repeats on the "
              "states the tree visits; tree and network fly the same evaluation episodes. Target of the distillation: depth "
              "<= 6, fidelity >= 95 %, success within 5 points of the network's.", "",
              "| scenario | seed | depth | leaves | fidelity | tree success | network success | tree collision rate "
              "| target met | files |", "|---|---|---|---|---|---|---|---|---|---|"]
    texts: list[str] = []
    for stem, t in trees.items():
        why = _status(t)
        if why:
            lines.append(f"| `{stem}` | {why} | | | | | | | | |")
            continue
        lines.append(f"| `{stem}` | {t['seed']} | {t['depth']} | {t['leaves']} | {_pct(t['fidelity'])} "
                     f"| {_pct(t['success'])} | {_pct(t['network_success'])} | {_pct(t['crash'])} "
                     f"| {'yes' if t['meets_target'] else 'no'} | [text]({t['text_file']}), [rules]({t['rules_file']}) |")
        texts += [f"<details><summary>`{stem}` tree</summary>", "", "```", t["text"], "```", "", "</details>", ""]
    return lines + [""] + texts


def _per_seed(results: dict[str, Any]) -> list[str]:
    lines = ["## Per seed", ""]
    groups = [(f"`{stem}`", results[stem]) for stem in scenario_stems(results)]
    groups += [(f"{name} (with the `{c['from']}` network)", c["with"]) for name, c in (results.get("transfer") or {}).items()]
    for title, group in groups:
        if not group["seeds"]:
            continue
        lines += [f"<details><summary>{title}</summary>", "",
                  "| seed | greedy success | collision rate | episodes to 90 % | wall time to 90 % | CPU time to 90 % "
                  "| episodes trained | budget | run CPU time | best checkpoint after | run |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for s in group["seeds"]:
            lines.append(f"| {s['seed']} | {_pct(s['greedy_success'])} | {_pct(s['collision_rate'])} "
                         f"| {_num(s['episodes_to_90'])} | {_duration(s['wall_s'])} | {_duration(s.get('cpu_s'))} "
                         f"| {s['episodes']} | {s['budget']} | {_duration(s.get('cpu_total_s'))} "
                         f"| {s['checkpoint_episode']} | `{s['run_dir']}` |")
        if group.get("unfinished"):
            lines.append(f"\nNot finished: seeds {', '.join(map(str, group['unfinished']))}.")
        lines += ["", "</details>", ""]
    return lines


def _definitions(meta: dict[str, Any]) -> list[str]:
    return [
        "## Definitions", "",
        f"- **Greedy success / collision rate**: share of drone-episodes that reached the goal / crashed when "
        f"the run's best checkpoint (the network of its best periodic greedy evaluation, "
        f"`best.safetensors`) flies {meta['eval_episodes']} episodes greedily on reset seeds "
        f"`eval_seeds({EVAL_SEED_BASE} + seed, n)`, held out from the periodic evaluations that chose it and "
        "the same for a seed's runs with and without transfer. Mean over seeds with a Student-t 95 % "
        "interval (clipped to [0, 1]); collision rate: mean over seeds.",
        f"- **Episodes to 90 %**: training episodes when the run's periodic greedy evaluation (every "
        f"`eval_every` episodes of the scenario's `train:` section, and at the end) first reached "
        f"{100 * THRESHOLD:.0f} %; its resolution is `eval_every`. Median over the seeds that reached it.",
        f"- **Held 90 % to the end**: of the seeds that reached {100 * THRESHOLD:.0f} %, those whose last periodic "
        "evaluation (where training ended: the budget, or an early stop on success) was still there; a collapse "
        "after solving shows here.",
        "- **Wall time to 90 %**: wall-clock seconds of training and its greedy evaluations until then, "
        f"with {_parallel(meta)} (they share the CPU). Median over the seeds that reached it.",
        "- **CPU time** (per seed): CPU seconds of the training process (simulation, learning and greedy "
        "evaluations; torch on one thread by default) until 90 % and for the whole run: the wall time the "
        "run needs on one core of its own, however busy this machine was; '-' for runs logged before it "
        "was recorded.",
        "- **Comparison test**: Mann-Whitney U (two-sided, scipy) on episodes to 90 %, runs that never "
        "reached it counted as their episode budget.",
        _seed_sets(),
        *_report_flights(meta),
        "",
    ]


def _seed_sets() -> str:
    """The named sets of evaluation episodes (`rl.experiments.seeds`): what each one decides."""
    return (f"- **Episode sets** (reset seeds `eval_seeds(base + offset, n)`, disjoint sets): choosing "
            f"`eval_seeds({SEED_BASES['choosing']} + seed, n)`, the periodic evaluations during training that pick "
            f"the best checkpoint; evaluation `eval_seeds({SEED_BASES['evaluation']} + seed, n)`, the greedy success "
            f"reported here and `sitl-bridge eval`'s default; mining `eval_seeds({SEED_BASES['mining']}, n)`, the "
            f"episodes behaviour and rules are mined from; verification `eval_seeds({SEED_BASES['verification']}, n)`, "
            "the episodes the rules files are verified on and `sitl-bridge eval --rules`'s default.")


def _report_flights(meta: dict[str, Any]) -> list[str]:
    """What the behaviour, rules, trees and pictures flew (the experiment file's `report:` section)."""
    settings = meta.get("report")
    if not settings:
        return []
    return [f"- **Report flights** (the experiment file's `report:` section; reset seeds `eval_seeds({EVAL_SEED_BASE}, n)` "
            f"for pictures, trees and backends, the mining and verification sets for behaviour and rules, "
            "cached per scenario in `rules/`, `trees/`, `figures/` while the checkpoints are the same): behaviour "
            f"{settings['behaviour_episodes']} greedy episodes per seed; rules YAMLs {settings['verify_episodes']} "
            f"episodes per scenario flown; trees depth <= {settings['distill_depth']}, {settings['distill_iterations']} "
            f"DAgger iterations of {settings['distill_episodes']} episodes, best seed only; pictures "
            f"{settings['picture_episodes']} greedy episodes per seed, up to {settings['picture_cells']} drawn; "
            f"backends {settings.get('backend_episodes', '?')} greedy episodes per seed and backend, "
            f"{settings.get('backend_seeds') or 'all'} seeds (cached in `backends/`)."]


def _parallel(meta: dict[str, Any]) -> str:
    workers = sorted({i["workers"] for i in meta.get("training") or [] if i.get("trained")})
    if not workers:
        return "the runs in parallel that trained them"
    shown = " to ".join(map(str, [workers[0], workers[-1]] if len(workers) > 1 else workers))
    return f"{shown} runs training in parallel on one machine (`--workers`, in {len(meta['training'])} invocations)"


def write_report(results: dict[str, Any], meta: dict[str, Any], out: str | Path) -> Path:
    """RESULTS.md in `out` (results.json and experiment.json are written by the caller)."""
    from sitl_bridge.rl.common.atomic import atomic_write_text

    path = Path(out) / RESULTS_MD
    atomic_write_text(path, render(results, meta))
    return path


def meta_of(experiment: Experiment, out: str | Path, command: str, sections_not_run: dict[str, str]) -> dict[str, Any]:
    """experiment.json: how the results were made."""
    import dataclasses
    import time

    from sitl_bridge import __version__
    from sitl_bridge.rl.experiments.runner import invocations
    from sitl_bridge.rl.training.run_dir import source_commit

    seeds = experiment.seeds
    return {
        "name": experiment.name, "file": experiment.source, "command": command,
        "seeds": list(seeds), "seeds_text": _seed_text(list(seeds)),
        "scenario_seeds": {s.stem: list(s.seeds) for s in experiment.scenarios if s.seeds is not None},
        "eval_episodes": experiment.eval_episodes, "threshold": THRESHOLD, "eval_seed_base": EVAL_SEED_BASE,
        "seed_bases": SEED_BASES,
        "autopilot": experiment.autopilot, "training": invocations(out), "version": __version__,
        "git_commit": source_commit(), "written": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "sections_not_run": sections_not_run, "report": dataclasses.asdict(experiment.report),
    }
