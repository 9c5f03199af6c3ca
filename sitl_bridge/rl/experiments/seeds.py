"""The named seed bases of every set of evaluation episodes, in a module of their own: the results
and every report section use them, and the results module imports the sections.

Each set is `rl.evaluation.rollout.eval_seeds(BASE + offset, n)`; a different first argument
gives an independent stream of reset seeds, so the sets below share no episode as long as run
seeds stay below `SEED_BASE_SPACING` (`disjoint_seed_sets` checks that the report's sets do):

- choosing: `CHOOSE_SEED_BASE + run seed`, the periodic evaluations during training that pick a
  run's best checkpoint (`rl.training.trainer`), so in-sample for that checkpoint;
- evaluation: `EVAL_SEED_BASE + run seed`, the report's greedy evaluation of each best checkpoint
  and `sitl-bridge eval`'s default;
- mining: `MINE_SEED_BASE`, the episodes the behaviour analysis flies and mines rules from;
- verification: `VERIFY_SEED_BASE`, the episodes a mined rule set is verified on, and
  `sitl-bridge eval --rules`'s default.
"""

from __future__ import annotations

SEED_BASE_SPACING = 1_000_000
"""Distance between two bases: the run seeds (offsets) must stay below it."""
CHOOSE_SEED_BASE = 0
"""Periodic evaluations during training (`eval_seeds(run seed, n)`): they choose `best.safetensors`."""
EVAL_SEED_BASE = 1 * SEED_BASE_SPACING
"""Evaluation seeds of the report: `eval_seeds(EVAL_SEED_BASE + seed, n)`, held out from the
periodic evaluations (`eval_seeds(seed, n)`) that picked the best checkpoint."""
MINE_SEED_BASE = 2 * SEED_BASE_SPACING
"""Behaviour analysis and rule mining: `eval_seeds(MINE_SEED_BASE, n)` for every run."""
VERIFY_SEED_BASE = 3 * SEED_BASE_SPACING
"""Verification of mined rule sets: `eval_seeds(VERIFY_SEED_BASE, n)`, none of the mining episodes."""
SEED_BASES = {"choosing": CHOOSE_SEED_BASE, "evaluation": EVAL_SEED_BASE, "mining": MINE_SEED_BASE,
              "verification": VERIFY_SEED_BASE}
"""Every named base, as the report lists them."""


def seed_set(base: int, run_seed: int = 0) -> int:
    """The first argument of `eval_seeds` for the set at `base` of run `run_seed` (a clear error
    when the run seed would reach into the next set)."""
    if not 0 <= run_seed < SEED_BASE_SPACING:
        raise ValueError(f"run seed: expected 0..{SEED_BASE_SPACING - 1} (the evaluation seed sets are "
                         f"{SEED_BASE_SPACING} apart), got {run_seed}")
    return base + run_seed


def disjoint_seed_sets(run_seeds: list[int], episodes: int) -> bool:
    """Whether the choosing and evaluation episodes of `run_seeds` and the mining and verification
    episodes, `episodes` of each, share no reset seed."""
    from sitl_bridge.rl.evaluation.rollout import eval_seeds

    sets = [eval_seeds(seed_set(base, s), episodes) for base in (CHOOSE_SEED_BASE, EVAL_SEED_BASE) for s in run_seeds]
    sets += [eval_seeds(MINE_SEED_BASE, episodes), eval_seeds(VERIFY_SEED_BASE, episodes)]
    every = [seed for chosen in sets for seed in chosen]
    return len(set(every)) == len(every)
