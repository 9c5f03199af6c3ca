"""`sitl-bridge train WORLD.yaml`: train an agent on a scenario, crash-safe and resumable.

`--algorithm` picks the learner: dqn (default, the project's own) or ppo, sac, td3
(Stable-Baselines3, the `sb3` extra; their constructor arguments come from the scenario's
`train: {ppo: {...}}` mapping). Hyperparameters come from the scenario's `train:` section; every
DQN one and the run-wide ones can be overridden here (`--gamma 0.95`, `--episodes 500`, ... see
`--help`); the command line wins over `train: {algorithm: ...}`. `--resume RUN_DIR` continues a run (killed or
finished, e.g. with a larger `--episodes`); `--init-from` starts from another run's network.
"""

from __future__ import annotations

import argparse
import errno
import sys
from typing import TYPE_CHECKING

from sitl_bridge.commands import add_env_autopilot_argument
from sitl_bridge.errors import ConfigError
from sitl_bridge.rl.learner.config import (
    add_config_arguments,
    load_train_config,
    overrides_from_args,
)

if TYPE_CHECKING:
    from sitl_bridge.rl.training.trainer import Trainer

def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("train", help="train a DQN, PPO, SAC or TD3 agent on a scenario (resumable)",
                                   description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("world", nargs="?", help="scenario file, or a shipped world by name (obstacle); not needed with --resume")
    add_env_autopilot_argument(parser)
    parser.add_argument("--standby", action="store_true",
                        help="px4: keep a standby PX4 booted to take over crashed episodes (faster "
                             "with a free core; docs/autopilots.md, Standby)")
    parser.add_argument("--seed", type=int, default=0, help="run seed (network, exploration, episodes)")
    parser.add_argument("--out", default="runs", help="folder for the run directory (default runs/)")
    parser.add_argument("--resume", metavar="RUN_DIR", help="continue this run from its newest good checkpoint")
    parser.add_argument("--init-from", metavar="RUN_DIR_OR_CHECKPOINT",
                        help="start from this run's network (curriculum; epsilon from transfer_epsilon_max)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    _add_watchdog_arguments(parser)
    add_config_arguments(parser)
    parser.set_defaults(func=main)


def _add_watchdog_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("watchdog (rl/training/watchdog.py)")
    group.add_argument("--watchdog", action="store_true",
                       help="train in a child process; restart it from its last checkpoint when it dies or freezes")
    group.add_argument("--freeze-timeout", type=float, default=120.0, metavar="S",
                       help="with --watchdog: no heartbeat progress for S seconds counts as frozen (default 120)")
    group.add_argument("--max-restarts-per-hour", type=int, default=10, metavar="N",
                       help="with --watchdog: stop with a report after N restarts within an hour (default 10)")


def _run_watchdog(args: argparse.Namespace) -> int:
    from sitl_bridge.rl.training.watchdog import Watchdog

    if args.freeze_timeout <= 0 or args.max_restarts_per_hour < 0:
        print("error: command line: --freeze-timeout/--max-restarts-per-hour: expected positive numbers",
              file=sys.stderr)
        return 2
    argv = [a for a in sys.argv[sys.argv.index("train") + 1:] if a != "--watchdog"]
    report = Watchdog(argv, args.freeze_timeout, args.max_restarts_per_hour).run()
    print(f"watchdog: {len(report.restarts)} restart(s)" + (f"; stopped: {report.gave_up}" if report.gave_up else "")
          + (f"; log: {report.run_dir}/watchdog.jsonl" if report.restarts else ""), file=sys.stderr)
    return report.exit_code


def main(args: argparse.Namespace) -> int:
    if args.watchdog:
        return _run_watchdog(args)
    try:
        return _train(args)
    except OSError as exc:
        if exc.errno not in (errno.ENOSPC, errno.EDQUOT):
            raise
        # Every write is atomic (rl/common/atomic.py): what was saved before stays; --resume continues.
        print(f"error: disk full writing {exc.filename or 'the run directory'}: free some space, then "
              "`sitl-bridge train --resume RUN_DIR` continues from the last checkpoint", file=sys.stderr)
        return 1


def _train(args: argparse.Namespace) -> int:
    # torch and the simulator load here, not when the CLI lists its commands.
    from sitl_bridge.rl.learner.checkpoint import CheckpointError
    from sitl_bridge.rl.training.init_from import ShapeMismatch
    from sitl_bridge.rl.training.train_plan import plan_lines

    try:
        trainer = _build(args)
    except (ConfigError, CheckpointError, ShapeMismatch) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    with trainer:
        resumed = trainer.episode > 0
        print(f"run directory: {trainer.run_dir}" + (f" (resuming after episode {trainer.episode})"
                                                     if resumed else ""), file=sys.stderr)
        for line in plan_lines(trainer.config, trainer.episode):
            print(line, file=sys.stderr)
        result = trainer.train()
        print(f"this session: {result.episodes_this_session} episodes ({result.steps_this_session} steps) in "
              f"{result.wall_time_s:.1f} s; run total: {result.episodes} of {trainer.config.episodes} episodes "
              f"({result.global_step} steps); success while exploring (last {trainer.config.success_window} "
              f"drone-episodes): {result.success_rate:.0%}")
        if trainer.stopped_early and trainer.last_eval is not None:
            baseline = trainer.constant_baseline()
            print(f"stopped early: greedy success reached {trainer.config.stop_on_success:.0%} and beats the best "
                  f"constant action ({baseline.action}: {baseline.success_rate:.0%})")
            print("greedy evaluation: " + trainer.last_eval.summary())
        elif result.episodes >= trainer.config.episodes and trainer.config.eval_episodes > 0:
            final = trainer.recorded_evaluation() or trainer.evaluate()  # done before a kill: not again
            print("greedy evaluation: " + final.summary())
    return 0


def _build(args: argparse.Namespace) -> Trainer:
    from sitl_bridge.rl.common.drones_env import scenario_env_factory
    from sitl_bridge.rl.training.run_dir import RunSpec
    from sitl_bridge.rl.training.runs import resume_run, start_run

    overrides = overrides_from_args(args)
    progress = not args.no_progress
    if args.resume:
        if any(v is not None for k, v in overrides.items() if k != "episodes"):
            raise ConfigError("command line: only --episodes can change when resuming (the run's "
                              "config.yaml holds its hyperparameters)")
        return resume_run(args.resume, episodes=overrides["episodes"], progress=progress, heartbeat=True)
    if not args.world:
        raise ConfigError("command line: WORLD: expected a scenario file (or --resume RUN_DIR), got nothing")
    from sitl_bridge.rl.training.scenario_file import check_scenario_file
    from sitl_bridge.world.lookup import world_file

    args.world = str(world_file(args.world))  # a shipped world by bare name; run.json records the file
    check_scenario_file(args.world, need_task=True)  # every section, before a run directory exists
    if args.standby:
        from sitl_bridge.envs.options import EnvOptions

        try:
            EnvOptions.of(autopilot=args.autopilot, standby=True)
        except ValueError as exc:
            raise ConfigError(f"--standby: {exc}") from None
    config = load_train_config(args.world, overrides)
    spec = RunSpec(world=args.world, autopilot=args.autopilot, seed=args.seed, init_from=args.init_from,
                   standby=args.standby)
    factory = scenario_env_factory(args.world, args.autopilot, **({"standby": True} if args.standby else {}))
    return start_run(args.out, spec, config, factory, progress=progress, heartbeat=True)
