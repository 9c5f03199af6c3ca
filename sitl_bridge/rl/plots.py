"""Learning curves of a run (from its episode log): reward, success rate, epsilon, loss."""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from sitl_bridge.rl.episode_log import read_records
from sitl_bridge.rl.run_dir import EPISODES_FILE, EVAL_FILE, EVALS_FILE


def per_episode(records: list[dict]) -> dict[str, np.ndarray]:
    """Episode-level series (drones averaged): episode, reward, success, epsilon, loss, steps."""
    grouped: dict[int, list[dict]] = defaultdict(list)
    for record in records:
        grouped[record["episode"]].append(record)
    episodes = sorted(grouped)

    def series(fn) -> np.ndarray:  # noqa: ANN001 - small local helper
        return np.array([fn(grouped[e]) for e in episodes], dtype=float)

    return {
        "episode": np.array(episodes, dtype=float),
        "reward": series(lambda rs: np.mean([r["reward"] for r in rs])),
        "success": series(lambda rs: np.mean([r["outcome"] == "goal" for r in rs])),
        "crash": series(lambda rs: np.mean([r["outcome"] == "crash" for r in rs])),
        "epsilon": series(lambda rs: rs[0]["epsilon"]),
        "loss": series(lambda rs: np.nan if rs[0]["mean_loss"] is None else rs[0]["mean_loss"]),
        "steps": series(lambda rs: np.mean([r["steps"] for r in rs])),
        "wall_time_s": series(lambda rs: rs[0]["wall_time_s"]),
    }


def rolling_mean(values: np.ndarray, window: int) -> np.ndarray:
    """Mean of the finite values among the last `window` at each point (NaN where none)."""
    finite = np.isfinite(values)
    sums = np.cumsum(np.insert(np.where(finite, values, 0.0), 0, 0.0))
    counts = np.cumsum(np.insert(finite.astype(float), 0, 0.0))
    end = np.arange(1, len(values) + 1)
    start = np.maximum(end - window, 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (sums[end] - sums[start]) / (counts[end] - counts[start])


def _read_evals(run_dir: Path) -> list[dict]:
    path = run_dir / EVALS_FILE
    return [json.loads(line) for line in path.read_text().splitlines() if line] if path.exists() else []


def plot_run(run_dir: str | Path, out: str | Path | None = None, window: int = 50) -> Path:
    """Write the run's learning curves as a PNG (default RUN_DIR/learning_curves.png)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    run_dir = Path(run_dir)
    data = per_episode(read_records(run_dir / EPISODES_FILE))
    if len(data["episode"]) == 0:
        raise ValueError(f"{run_dir}: the episode log is empty, nothing to plot")
    x = data["episode"]
    fig, axes = plt.subplots(2, 2, figsize=(12, 8), sharex=True)
    ax = axes[0, 0]
    ax.plot(x, data["reward"], color="0.75", lw=0.6, label="episode")
    ax.plot(x, rolling_mean(data["reward"], window), color="C0", label=f"mean of {window}")
    ax.set_ylabel("cumulative reward")
    ax.legend(loc="lower right")
    ax = axes[0, 1]
    ax.plot(x, rolling_mean(data["success"], window), color="C2", label="goal")
    ax.plot(x, rolling_mean(data["crash"], window), color="C3", label="crash")
    evals = _read_evals(run_dir)
    if evals:
        ax.plot([e["after_episodes"] - 1 for e in evals], [e["success_rate"] for e in evals], "o",
                color="k", ms=4, label="greedy eval")
    ax.set_ylim(-0.02, 1.02)
    ax.set_ylabel(f"rate (last {window} episodes)")
    ax.legend(loc="center right")
    ax = axes[1, 0]
    ax.plot(x, data["epsilon"], color="C1")
    ax.set_ylabel("epsilon")
    ax.set_xlabel("episode")
    ax = axes[1, 1]
    loss = data["loss"]
    if np.any(np.isfinite(loss) & (loss > 0)):
        ax.semilogy(x, loss, color="0.75", lw=0.6)
        ax.semilogy(x, rolling_mean(loss, window), color="C4")
    ax.set_ylabel("mean loss")
    ax.set_xlabel("episode")
    title = run_dir.name
    eval_path = run_dir / EVAL_FILE
    if eval_path.exists():
        result = json.loads(eval_path.read_text())
        title += f"\ngreedy: success {result['success_rate']:.0%}, crash {result['crash_rate']:.0%} " \
                 f"({result['episodes']} episodes after {result.get('after_episodes', '?')})"
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    out = Path(out) if out else run_dir / "learning_curves.png"
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out
