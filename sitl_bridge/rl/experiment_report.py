"""RESULTS.md and its figures, made from results.json (and experiment.json: how it was made).

Figures (`DIR/figures/`): per scenario the learning curves of its seeds (`plots.plot_runs`, mean
and 95 % band), per comparison the transfer runs' curves and the greedy success with and without
the earlier network in one panel (`plots.plot_greedy_groups`).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from sitl_bridge.rl.experiment import RESERVED, Experiment
from sitl_bridge.rl.experiment_results import EVAL_SEED_BASE, THRESHOLD

FIGURES = "figures"
RESULTS_MD = "RESULTS.md"
RESULTS_JSON = "results.json"
META_JSON = "experiment.json"


def scenario_stems(results: dict[str, Any]) -> list[str]:
    """The scenario keys of results.json, in their order."""
    return [key for key in results if key not in RESERVED]


def write_figures(results: dict[str, Any], out: str | Path, say: Callable[[str], None] = print) -> None:
    """Draw every figure the results have runs for; record each one's path (relative to `out`)
    in its scenario's or comparison's object as `figure` (and `figure_with_runs`)."""
    from sitl_bridge.rl.plots import NotARun, plot_greedy_groups, plot_runs

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
    for name, comparison in results.get("transfer", {}).items():
        with_dirs = dirs(comparison["with"])
        if with_dirs:
            draw(f"transfer_{name}_with_runs", comparison, "figure_with_runs", lambda p, d=with_dirs: plot_runs(d, p))
        groups = {f"with the {comparison['from']} network": with_dirs,
                  "without (trained from scratch)": dirs(comparison["without"])}
        if any(groups.values()):
            draw(f"transfer_{name}", comparison, "figure", lambda p, g=groups, c=comparison: plot_greedy_groups(
                g, p, f"{c['to']}: greedy success with vs without the {c['from']} network (same seeds)"))


# -- formatting ----------------------------------------------------------------------------------
def _pct(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.0f} %"


def _ci(interval: list[float] | None) -> str:
    return "" if interval is None else f" [{100 * interval[0]:.0f}, {100 * interval[1]:.0f}]"


def _num(value: float | None, digits: int = 0) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


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
        f"Seeds {meta['seeds_text']} per scenario; each finished run's best checkpoint flown greedily for "
        f"{meta['eval_episodes']} episodes on held-out seeds (definitions at the end).",
        "",
    ]
    lines += _scenario_table(results) + _thesis_table(results) + _figures(results)
    lines += _transfer_section(results) + _rules_section(results, meta) + _trees_section(results, meta)
    lines += _per_seed(results) + _definitions(meta)
    return "\n".join(lines) + "\n"


def _scenario_table(results: dict[str, Any]) -> list[str]:
    lines = ["## Scenarios", "",
             "| scenario | seeds done | greedy success, mean [95 % CI] | collision rate | reached 90 % "
             "| episodes to 90 % (median) | wall time to 90 % (median) | thesis |",
             "|---|---|---|---|---|---|---|---|"]
    for stem in scenario_stems(results):
        r = results[stem]
        thesis = r.get("thesis") or {}
        done = len(r["seeds"])
        planned = done + len(r.get("unfinished", []))
        name = f"`{stem}`" + (f" ({thesis['shorthand']})" if thesis.get("shorthand") else "")
        if not done:
            lines.append(f"| {name} | 0/{planned} | not run | | | | | {_cell(thesis.get('result', '-'))} |")
            continue
        lines.append(f"| {name} | {done}/{planned} | {_pct(r['success_mean'])}{_ci(r['success_ci95'])} "
                     f"| {_pct(r['collision_mean'])} | {r['reached_90']}/{done} | {_num(r['episodes_to_90_median'])} "
                     f"| {_duration(r['wall_s_median'])} | {_cell(thesis.get('result', '-'))} |")
    return lines + [""]


def _thesis_table(results: dict[str, Any]) -> list[str]:
    rows = [(stem, results[stem].get("thesis") or {}) for stem in scenario_stems(results)]
    if not any(t for _, t in rows):
        return []
    lines = ["What the thesis reported beside ours: it gives no success rates, only whether learning "
             "was stable, from one or two runs per scenario, and the behaviour it found (action codes, "
             "its Table 2).", "",
             "| scenario | thesis | result | runs | behaviour found | source |", "|---|---|---|---|---|---|"]
    for stem, t in rows:
        lines.append(f"| `{stem}` | {_cell(t.get('shorthand', '-'))} | {_cell(t.get('result', 'not in the thesis'))} "
                     f"| {_cell(t.get('runs', '-'))} | {_cell(t.get('behaviour', '-'))} | {_cell(t.get('source', '-'))} |")
    return lines + [""]


def _figures(results: dict[str, Any]) -> list[str]:
    lines = ["## Learning curves", "",
             "Per scenario, every finished seed: greedy success during training, training outcomes, reward "
             "per term, exploration and loss (mean and 95 % band across seeds).", ""]
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
              "when the transfer runs needed fewer episodes.", "",
              "| comparison | seeds with / without | success with | success without | reached 90 % with / without "
              "| episodes to 90 % median with / without | U | p | effect size | answer | thesis |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, c in transfer.items():
        w, wo = c["with"], c["without"]
        lines.append(
            f"| {name}: `{c['from']}` -> `{c['to']}` | {len(w['seeds'])} / {len(wo['seeds'])} "
            f"| {_pct(w['success_mean'])}{_ci(w['success_ci95'])} | {_pct(wo['success_mean'])}{_ci(wo['success_ci95'])} "
            f"| {w['reached_90']} / {wo['reached_90']} | {_num(w['episodes_to_90_median'])} / "
            f"{_num(wo['episodes_to_90_median'])} | {_num(c['u'], 1)} | {_p(c['p_value'])} "
            f"| {_num(c['effect_size'], 2)} | {_answer(c)} | {_cell(_thesis_note(c.get('thesis') or {}))} |")
    lines.append("")
    for name, c in transfer.items():
        figures = [f"[{c[k]}]({c[k]})" for k in ("figure", "figure_with_runs") if c.get(k)]
        lines.append(f"- {name}: " + (", ".join(figures) if figures else "no figure (no finished runs)"))
    return lines + [""]


def _thesis_note(thesis: dict[str, str]) -> str:
    if not thesis:
        return "-"
    text = thesis.get("result", "-") + (f" ({thesis['runs']} runs)" if thesis.get("runs") else "")
    return text + (f"; {thesis['source']}" if thesis.get("source") else "")


def _answer(c: dict[str, Any]) -> str:
    if c["p_value"] is None:
        return "not run"
    faster = "fewer" if c["effect_size"] < 0 else "more"
    if c["p_value"] < 0.05:
        return f"transfer needed {faster} episodes (p < 0.05)"
    return "no significant difference at 5 %"


def _not_run(name: str, meta: dict[str, Any]) -> list[str]:
    reason = (meta.get("sections_not_run") or {}).get(name, "no results")
    return [f"Not run ({reason}).", ""]


def _rules_section(results: dict[str, Any], meta: dict[str, Any]) -> list[str]:
    lines = ["## Rules", ""]
    rules = results.get("rules")
    if rules is None:
        return lines + _not_run("rules", meta)
    lines += ["| rule | support (seeds, episodes) | verification: success / collision per scenario |",
              "|---|---|---|"]
    for rule in rules:
        checks = "; ".join(f"`{stem}` {_pct(v.get('success'))} / {_pct(v.get('collision_rate'))}"
                           for stem, v in (rule.get("verification") or {}).items() if isinstance(v, dict))
        lines.append(f"| {_cell(rule.get('text', '-'))} | {rule.get('support_seeds', '-')}, "
                     f"{rule.get('support_episodes', '-')} | {checks or '-'} |")
    return lines + [""]


def _trees_section(results: dict[str, Any], meta: dict[str, Any]) -> list[str]:
    lines = ["## Distilled decision trees", ""]
    trees = results.get("trees")
    if trees is None:
        return lines + _not_run("trees", meta)
    lines += ["| scenario | depth | fidelity | tree success | network success |", "|---|---|---|---|---|"]
    for stem, t in trees.items():
        lines.append(f"| `{stem}` | {t.get('depth', '-')} | {_pct(t.get('fidelity'))} | {_pct(t.get('success'))} "
                     f"| {_pct(t.get('network_success'))} |")
    return lines + [""]


def _per_seed(results: dict[str, Any]) -> list[str]:
    lines = ["## Per seed", ""]
    groups = [(f"`{stem}`", results[stem]) for stem in scenario_stems(results)]
    groups += [(f"{name} (with the `{c['from']}` network)", c["with"]) for name, c in (results.get("transfer") or {}).items()]
    for title, group in groups:
        if not group["seeds"]:
            continue
        lines += [f"<details><summary>{title}</summary>", "",
                  "| seed | greedy success | collision rate | episodes to 90 % | wall time to 90 % | episodes trained "
                  "| budget | best checkpoint after | run |", "|---|---|---|---|---|---|---|---|---|"]
        for s in group["seeds"]:
            lines.append(f"| {s['seed']} | {_pct(s['greedy_success'])} | {_pct(s['collision_rate'])} "
                         f"| {_num(s['episodes_to_90'])} | {_duration(s['wall_s'])} | {s['episodes']} | {s['budget']} "
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
        "- **Wall time to 90 %**: wall-clock seconds of training and its greedy evaluations until then, "
        f"with {_parallel(meta)} (they share the CPU). Median over the seeds that reached it.",
        "- **Comparison test**: Mann-Whitney U (two-sided, scipy) on episodes to 90 %, runs that never "
        "reached it counted as their episode budget.",
        "",
    ]


def _parallel(meta: dict[str, Any]) -> str:
    workers = sorted({i["workers"] for i in meta.get("training") or [] if i.get("trained")})
    if not workers:
        return "the runs in parallel that trained them"
    shown = " to ".join(map(str, [workers[0], workers[-1]] if len(workers) > 1 else workers))
    return f"{shown} runs training in parallel on one machine (`--workers`, in {len(meta['training'])} invocations)"


def write_report(results: dict[str, Any], meta: dict[str, Any], out: str | Path) -> Path:
    """RESULTS.md in `out` (results.json and experiment.json are written by the caller)."""
    from sitl_bridge.rl.atomic import atomic_write_text

    path = Path(out) / RESULTS_MD
    atomic_write_text(path, render(results, meta))
    return path


def meta_of(experiment: Experiment, out: str | Path, command: str, sections_not_run: dict[str, str]) -> dict[str, Any]:
    """experiment.json: how the results were made."""
    import time

    from sitl_bridge import __version__
    from sitl_bridge.rl.experiment import invocations
    from sitl_bridge.rl.run_dir import source_commit

    seeds = experiment.seeds
    contiguous = list(seeds) == list(range(seeds[0], seeds[-1] + 1))
    return {
        "name": experiment.name, "file": experiment.source, "command": command,
        "seeds": list(seeds), "seeds_text": f"{seeds[0]}-{seeds[-1]}" if contiguous and len(seeds) > 1
        else ", ".join(map(str, seeds)),
        "eval_episodes": experiment.eval_episodes, "threshold": THRESHOLD, "eval_seed_base": EVAL_SEED_BASE,
        "autopilot": experiment.autopilot, "training": invocations(out), "version": __version__,
        "git_commit": source_commit(), "written": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "sections_not_run": sections_not_run,
    }
