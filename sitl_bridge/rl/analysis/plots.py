"""Learning-curve figure of one run, or of several runs (seeds) as mean and 95 % band (where at
least `MIN_BAND_RUNS` runs contribute).

Four panels, each with its units:

1. greedy success over training: the periodic greedy evaluations (`evals.jsonl`, written every
   `eval_every` episodes), the measure of what the network has learned; exploration success is
   not shown here, since it falls as epsilon decays and reads as getting worse;
2. training outcome shares (goal, crash, out, timeout), stacked, as rolling means;
3. reward per term (and the total), rolling means;
4. epsilon (left axis) and the mean TD loss (right axis, log scale).
"""

from __future__ import annotations

import json
import os
import warnings
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from sitl_bridge.rl.analysis.figure_file import save_figure
from sitl_bridge.rl.common.episode_log import read_records
from sitl_bridge.rl.training.run_dir import BASELINE_FILE, EPISODES_FILE, EVALS_FILE, RUN_FILE

OUTCOMES = ("goal", "crash", "out", "timeout")
OUTCOME_COLOURS = {"goal": "C2", "crash": "C3", "out": "C1", "timeout": "0.6"}


class NotARun(ValueError):
    """The folder given is not a run directory, or its log holds nothing to plot."""


def per_episode(records: list[dict]) -> dict[str, np.ndarray]:
    """Episode-level series (drones averaged): episode, reward, outcome shares, epsilon, loss,
    steps, and `term:<name>` for every reward term."""
    grouped: dict[int, list[dict]] = defaultdict(list)
    for record in records:
        grouped[record["episode"]].append(record)
    episodes = sorted(grouped)

    def series(fn) -> np.ndarray:  # noqa: ANN001 - small local helper
        return np.array([fn(grouped[e]) for e in episodes], dtype=float)

    data = {
        "episode": np.array(episodes, dtype=float),
        "reward": series(lambda rs: np.mean([r["reward"] for r in rs])),
        "epsilon": series(lambda rs: rs[0]["epsilon"]),
        "loss": series(lambda rs: np.nan if rs[0]["mean_loss"] is None else rs[0]["mean_loss"]),
        "steps": series(lambda rs: np.mean([r["steps"] for r in rs])),
        "wall_time_s": series(lambda rs: rs[0]["wall_time_s"]),
    }
    for outcome in OUTCOMES:
        data[outcome] = series(lambda rs, o=outcome: np.mean([r["outcome"] == o for r in rs]))
    data["success"] = data["goal"]
    for term in sorted({t for r in records for t in r.get("reward_terms", {})}):
        data[f"term:{term}"] = series(lambda rs, t=term: np.mean([r.get("reward_terms", {}).get(t, 0.0) for r in rs]))
    return data


def rolling_mean(values: np.ndarray, window: int) -> np.ndarray:
    """Mean of the finite values among the last `window` at each point (NaN where none)."""
    finite = np.isfinite(values)
    sums = np.cumsum(np.insert(np.where(finite, values, 0.0), 0, 0.0))
    counts = np.cumsum(np.insert(finite.astype(float), 0, 0.0))
    end = np.arange(1, len(values) + 1)
    start = np.maximum(end - window, 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (sums[end] - sums[start]) / (counts[end] - counts[start])


def read_evals(run_dir: Path) -> list[dict]:
    """The run's greedy evaluations in order (lines that do not parse are skipped)."""
    path = run_dir / EVALS_FILE
    evals = []
    if path.exists():
        for line in path.read_text(errors="replace").splitlines():
            try:
                evals.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    return evals


def eval_series(run_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """(episodes trained, greedy success) of every evaluation of a run."""
    evals = read_evals(run_dir)
    return (np.array([e["after_episodes"] for e in evals], dtype=float),
            np.array([e["success_rate"] for e in evals], dtype=float))


def pad(curves: Sequence[np.ndarray]) -> np.ndarray:
    """The curves as rows of one array as long as the longest, NaN after a curve's end."""
    length = max(len(c) for c in curves)
    return np.vstack([np.pad(np.asarray(c, dtype=float), (0, length - len(c)), constant_values=np.nan)
                      for c in curves])


MIN_BAND_RUNS = 3
"""A band is drawn only where at least this many runs contribute: with two, Student's t
(12.7 at one degree of freedom) makes the band so wide it flattens every other line."""


def mean_and_band(curves: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean and 95 % confidence band (Student t) across runs, point by point, as long as the
    longest curve: where some curves have ended (or are NaN) the others make the mean, and the
    band is NaN (not drawn) where fewer than `MIN_BAND_RUNS` remain."""
    stacked = pad(curves)
    with warnings.catch_warnings():  # all-NaN columns (no loss yet) give NaN, as they should
        warnings.simplefilter("ignore", RuntimeWarning)
        mean = np.nanmean(stacked, axis=0)
        spread = np.nanstd(stacked, axis=0, ddof=1) if len(curves) >= 2 else np.full_like(mean, np.nan)
    from scipy import stats

    counts = np.sum(np.isfinite(stacked), axis=0)
    sem = spread / np.sqrt(np.maximum(counts, 1))
    half = np.where(counts >= MIN_BAND_RUNS, stats.t.ppf(0.975, np.maximum(counts - 1, 1)) * sem, np.nan)
    return mean, mean - half, mean + half


def held_evaluations(series: Sequence[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, list[np.ndarray]]:
    """Greedy-success curves of several runs on one grid (every episode count any run was
    evaluated at): each run's latest evaluation at or before a point, NaN before its first,
    and its last evaluation held after it ended (a run that stopped on success stays solved)."""
    grid = np.unique(np.concatenate([x for x, _ in series]))
    curves = []
    for x, y in series:
        order = np.argsort(x, kind="stable")
        index = np.searchsorted(x[order], grid, side="right") - 1
        curves.append(np.where(index >= 0, y[order][np.maximum(index, 0)], np.nan))
    return grid, curves


def _load(run_dir: Path) -> dict[str, np.ndarray]:
    if not (run_dir / RUN_FILE).is_file():
        raise NotARun(f"{run_dir}: not a run directory (no {RUN_FILE})")
    data = per_episode(read_records(run_dir / EPISODES_FILE))
    if len(data["episode"]) == 0:
        raise NotARun(f"{run_dir}: the episode log is empty, nothing to plot")
    return data


def plot_runs(run_dirs: Sequence[str | Path], out: str | Path | None = None, window: int = 50) -> Path:
    """Write the learning-curve figure of one run, or of several runs (mean and 95 % band
    across them), as a PNG (default: RUN_DIR/learning_curves.png of the first run)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dirs = [Path(d) for d in run_dirs]
    runs = [_load(d) for d in dirs]
    lengths = sorted(len(r["episode"]) for r in runs)
    shortest, longest = lengths[0], lengths[-1]
    window = max(1, min(window, longest))
    x = np.arange(1, longest + 1, dtype=float)  # episodes trained so far
    several = len(runs) > 1
    ragged = shortest != longest  # runs stopped early (on success): the others carry the curves on
    smooth = f"rolling mean over {window} episode{'s' if window > 1 else ''}"

    def draw(ax, curves: list[np.ndarray], xs: np.ndarray, colour: str, label: str,
             rate: bool = False, **style) -> None:
        mean, low, high = mean_and_band(curves)
        if rate:  # a share: the t band of a mean near 0 or 1 must not leave [0, 1]
            low, high = np.clip(low, 0.0, 1.0), np.clip(high, 0.0, 1.0)
        ax.plot(xs[:len(mean)], mean, color=colour, label=label, **style)
        if several:
            ax.fill_between(xs[:len(mean)], low, high, color=colour, alpha=0.2, lw=0)

    fig, axes = plt.subplots(2, 2, figsize=(13, 8.5), sharex=True)

    ax = axes[0, 0]
    evals = [eval_series(d) for d in dirs]
    if all(len(e[0]) for e in evals):
        grid, curves = held_evaluations(evals)
        label = "greedy success" + (f" (mean, 95 % band where >= {MIN_BAND_RUNS} runs)" if several else "")
        if several and ragged:
            label += ";\na run that ended holds its last evaluation"  # two lines: fits the panel
        draw(ax, curves, grid, "k", label, rate=True, marker="o", ms=3)
    else:
        ax.text(0.5, 0.5, "no greedy evaluations logged\n(train: eval_every)", ha="center", va="center",
                transform=ax.transAxes, color="0.4")
    baselines = [json.loads((d / BASELINE_FILE).read_text()) for d in dirs if (d / BASELINE_FILE).is_file()]
    if baselines:
        best = max(b["success_rate"] for b in baselines)
        ax.axhline(best, color="C3", ls="--", lw=1,
                   label=f"best constant action ({best:.0%}): what learning must beat")
    ax.set_ylim(-0.02, 1.02)
    ax.set_ylabel("greedy success rate (share of drone-episodes)")
    ax.set_title("greedy evaluation during training", fontsize=10)
    ax.legend(loc="lower right", fontsize=8)

    ax = axes[0, 1]
    shares = {o: mean_and_band([rolling_mean(r[o], window) for r in runs])[0] for o in OUTCOMES}
    ax.stackplot(x, [shares[o] for o in OUTCOMES], labels=OUTCOMES,
                 colors=[OUTCOME_COLOURS[o] for o in OUTCOMES], alpha=0.85)
    ax.set_ylim(0, 1)
    ax.set_ylabel(f"training outcome share ({smooth})")
    ax.set_title("training episodes (with exploration)" + ("; means over the runs still training" if ragged else ""),
                 fontsize=10)
    ax.legend(loc="center left", fontsize=8, framealpha=0.9)

    ax = axes[1, 0]
    terms = sorted({k for r in runs for k in r if k.startswith("term:")})
    draw(ax, [rolling_mean(r["reward"], window) for r in runs], x, "k", "total", lw=2)
    for i, term in enumerate(terms):
        curves = [rolling_mean(r.get(term, np.zeros(len(r["episode"]))), window) for r in runs]
        draw(ax, curves, x, f"C{i % 10}", term.split(":", 1)[1])
    ax.set_ylabel(f"reward per episode ({smooth})")
    ax.set_xlabel("episodes trained")
    ax.set_title("reward per term", fontsize=10)
    low, high = ax.get_ylim()
    ax.set_ylim(low, high + 0.35 * (high - low))  # room for the legend above the curves
    ax.legend(loc="upper left", fontsize=7, ncol=4, framealpha=0.9)

    ax = axes[1, 1]
    draw(ax, [r["epsilon"] for r in runs], x, "C1", "epsilon (exploration)", rate=True)
    ax.set_ylim(0, 1.02)
    ax.set_ylabel("epsilon (probability of a random action)")
    ax.set_xlabel("episodes trained")
    loss_ax = ax.twinx()
    losses = [rolling_mean(r["loss"], window) for r in runs]
    if any(np.any(np.isfinite(c) & (c > 0)) for c in losses):
        # On a log axis the band is taken over log10(loss): a geometric mean and band.
        with np.errstate(divide="ignore", invalid="ignore"):
            logs = [np.where(c > 0, np.log10(c), np.nan) for c in losses]
        mean, low, high = mean_and_band(logs)
        loss_ax.semilogy(x, 10.0 ** mean, color="C4", label=f"TD loss ({smooth})")
        if several:
            loss_ax.fill_between(x, 10.0 ** low, 10.0 ** high, color="C4", alpha=0.2, lw=0)
    loss_ax.set_ylabel("mean TD loss per update (log)")
    handles = ax.get_legend_handles_labels()
    loss_handles = loss_ax.get_legend_handles_labels()
    ax.legend(handles[0] + loss_handles[0], handles[1] + loss_handles[1], loc="lower left", fontsize=8,
              framealpha=0.9)
    ax.set_title("exploration and loss", fontsize=10)

    # several runs: what their names share (scenario and experiment), not a list that runs off the page
    title = dirs[0].name if not several else \
        f"{len(dirs)} runs of {os.path.commonprefix([d.name for d in dirs]).rstrip('_') or 'several scenarios'}"
    fig.suptitle(title + (f"  ({shortest}-{longest} episodes)" if ragged else f"  ({longest} episodes)"), fontsize=10)
    fig.tight_layout()
    out = Path(out) if out else dirs[0] / "learning_curves.png"
    save_figure(fig, out, dpi=100)
    plt.close(fig)
    return out


def plot_greedy_groups(groups: dict[str, Sequence[str | Path]], out: str | Path, title: str = "") -> Path:
    """One panel: the greedy success of each group of runs (e.g. with and without a transferred
    network) over episodes trained, mean and 95 % band across each group's runs; a run that
    ended holds its last evaluation. Writes a PNG to `out`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.5))
    for i, (label, run_dirs) in enumerate(groups.items()):
        evals = [s for s in (eval_series(Path(d)) for d in run_dirs) if len(s[0])]
        if not evals:
            continue
        grid, curves = held_evaluations(evals)
        mean, low, high = mean_and_band(curves)
        ax.plot(grid, mean, color=f"C{i}", marker="os^D"[i % 4], ms=4, ls=("-", "--", ":", "-.")[i % 4],
                label=f"{label} ({len(evals)} runs)")  # distinct marks: equal curves stay visible
        if len(evals) > 1:
            ax.fill_between(grid, np.clip(low, 0.0, 1.0), np.clip(high, 0.0, 1.0), color=f"C{i}", alpha=0.2, lw=0)
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel("episodes trained (in this scenario)")
    ax.set_ylabel("greedy success rate (share of drone-episodes)")
    ax.set_title(title or "greedy evaluation during training", fontsize=10)
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="lower right", fontsize=8, title=f"mean, 95 % band where >= {MIN_BAND_RUNS} runs; ended runs hold their last value",
                  title_fontsize=7)
    fig.tight_layout()
    save_figure(fig, out, dpi=100)
    plt.close(fig)
    return Path(out)


def plot_run(run_dir: str | Path, out: str | Path | None = None, window: int = 50) -> Path:
    """The learning-curve figure of one run (see `plot_runs`)."""
    return plot_runs([run_dir], out, window)
