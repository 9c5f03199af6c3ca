"""What a training run is going to do, said before it does it (the first lines of `train`).

A newcomer reads `--episodes 150` as "150 episodes"; it is a cap that early stopping may cut
short, and the constant-action baseline flies many evaluation episodes before the first
periodic evaluation can report. These lines state both up front.
"""

from __future__ import annotations

from sitl_bridge.rl.learner.config import TrainConfig


def plan_lines(config: TrainConfig, done: int = 0) -> list[str]:
    """The run's plan: the episode cap, the evaluation cadence, whether and when it stops early."""
    left = max(config.episodes - done, 0)
    lines = [f"plan: at most {config.episodes} training episodes (--episodes is a cap)"
             + (f", {left} left after episode {done}" if done else "")]
    if config.algorithm != "dqn":
        lines.append(f"plan: {config.algorithm} (Stable-Baselines3) with train.{config.algorithm} = "
                     f"{config.sb3_arguments or '{}'} (SB3's defaults for the rest)")
        if config.unused_dqn_settings():
            lines.append(f"plan: not used by {config.algorithm} (DQN's hyperparameters; set them under "
                         f"train.{config.algorithm}): {', '.join(config.unused_dqn_settings())}")
    evaluates = config.eval_every > 0 and config.eval_episodes > 0
    if evaluates:
        lines.append(f"plan: a greedy evaluation of {config.eval_episodes} episodes every {config.eval_every} "
                     "training episodes; the first one also measures the constant-action baseline once")
    if config.stop_on_success and evaluates:
        confirm = (f" (confirmed by {config.stop_confirm_episodes} more evaluation episodes)"
                   if config.stop_confirm_episodes else "")
        lines.append(f"plan: stops early at the first periodic evaluation that reaches "
                     f"{config.stop_on_success:.0%} success{confirm} and beats the best constant action; "
                     f"otherwise it trains all {config.episodes}")
    elif config.stop_on_success:
        lines.append(f"plan: no early stopping: stop_on_success {config.stop_on_success:g} needs "
                     f"eval_every > 0; trains all {config.episodes}")
    else:
        lines.append(f"plan: no early stopping (stop_on_success 0): trains all {config.episodes}")
    if config.eval_episodes > 0:
        lines.append(f"plan: a final greedy evaluation of {config.eval_episodes} episodes when the budget is used up")
    return lines


def baseline_notice(n_actions: int, episodes: int) -> str:
    """The line printed before the constant-action baseline flies (it can take minutes)."""
    return (f"measuring the constant-action baseline: each of the {n_actions} actions flown greedily "
            f"for {episodes} evaluation episodes ({n_actions * episodes} episodes, once per run)")
