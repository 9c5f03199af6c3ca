#!/usr/bin/env python3
"""Slim a results tree (`docs/results` by default) to what its report and pictures need.

    python3 tools/slim_results.py [DIR ...] [--episodes-only] [--measure]

In every run directory (a folder with `run.json`) under each DIR:
- `episodes.jsonl` -> `episodes.jsonl.xz` (removed only after the archive reads back as its bytes);
- `best.safetensors` (a training checkpoint: optimizer state, replay priorities) is replaced by
  the policy-only export of its network under the same name, written aside and verified against
  the checkpoint's Q values before it takes the checkpoint's place; `checkpoints/` and `replay/`
  go after that (they resume training; a report never reads them);
- the report's caches keyed on the old checkpoint file's sha256 (caches written before they were
  keyed on the network's tensors) are re-keyed to the network's digest, so the report rebuilt
  from the slim tree reuses every cached flight instead of flying it again.
`--episodes-only` compresses the logs and leaves the networks; `--measure` changes nothing and
prints the bytes before and after.
"""

from __future__ import annotations

import argparse
import hashlib
import lzma
import shutil
import sys
from collections.abc import Iterator
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from sitl_bridge.rl.common.episode_files import compress_log  # noqa: E402
from sitl_bridge.rl.learner.checkpoint import BEST_CHECKPOINT, CHECKPOINT_DIR, CheckpointError  # noqa: E402
from sitl_bridge.rl.learner.policy_file import PolicyFileError, is_policy_file, network_digest  # noqa: E402
from sitl_bridge.rl.training.policy_export import export_policy, policy_export_bytes  # noqa: E402
from sitl_bridge.rl.training.run_dir import EPISODES_FILE, REPLAY, RUN_FILE  # noqa: E402

DEFAULT_TREE = REPO / "docs" / "results"


def run_dirs(tree: Path) -> Iterator[Path]:
    for run_file in sorted(tree.rglob(RUN_FILE)):
        yield run_file.parent


def _size(path: Path) -> int:
    if path.is_file():
        return path.stat().st_size
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) if path.is_dir() else 0


Sizes = dict[str, list[int]]
"""Bytes before and after, per kind of slimmed part (`episode logs`, `networks`)."""


def _count(sizes: Sizes, kind: str, before: int, after: int) -> None:
    total = sizes.setdefault(kind, [0, 0])
    total[0] += before
    total[1] += after


def measure(run: Path, episodes_only: bool, sizes: Sizes) -> None:
    """Bytes the run's slimmed parts weigh now and would weigh after (nothing written)."""
    log = run / EPISODES_FILE
    if log.is_file():
        data = log.read_bytes()
        _count(sizes, "episode logs", len(data), len(lzma.compress(data, preset=9 | lzma.PRESET_EXTREME)))
    best = run / BEST_CHECKPOINT
    if not episodes_only and best.is_file():
        before = best.stat().st_size + _size(run / CHECKPOINT_DIR) + _size(run / REPLAY)
        _count(sizes, "networks", before,
               best.stat().st_size if is_policy_file(best) else len(policy_export_bytes(best)[-1]))


def slim(run: Path, episodes_only: bool, rekeyed: dict[str, str], sizes: Sizes) -> None:
    """Slim one run (see the module docstring); records old file digest -> network digest."""
    log = run / EPISODES_FILE
    if log.is_file():
        _count(sizes, "episode logs", *compress_log(log))
    best = run / BEST_CHECKPOINT
    if best.is_file() and not is_policy_file(best):
        file_digest = hashlib.sha256(best.read_bytes()).hexdigest()
        _, state, network, _, _ = policy_export_bytes(best)
        rekeyed[file_digest] = network_digest(network, state["network"])
        if not episodes_only:
            size = best.stat().st_size
            export = export_policy(best, best)  # written aside, verified, then in place
            _count(sizes, "networks", size, export.bytes)
    if not episodes_only and best.is_file():
        for name in (CHECKPOINT_DIR, REPLAY):
            if (run / name).is_dir():
                _count(sizes, "networks", _size(run / name), 0)
                shutil.rmtree(run / name)


def rekey_caches(tree: Path, rekeyed: dict[str, str]) -> int:
    """Replace old checkpoint-file digests by network digests in the tree's JSON files (a sha256
    hex string names one file's bytes, so it matches nothing else). Returns files rewritten."""
    rewritten = 0
    for path in sorted(tree.rglob("*.json")):
        text = path.read_text()
        new = text
        for old, digest in rekeyed.items():
            new = new.replace(old, digest)
        if new != text:
            path.write_text(new)
            rewritten += 1
    return rewritten


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("dirs", nargs="*", type=Path, default=[DEFAULT_TREE], metavar="DIR",
                        help="results trees (default docs/results)")
    parser.add_argument("--episodes-only", action="store_true", help="compress the episode logs only")
    parser.add_argument("--measure", action="store_true", help="print the bytes before/after; change nothing")
    args = parser.parse_args(argv)
    sizes: Sizes = {}
    for tree in args.dirs:
        if not tree.is_dir():
            print(f"error: {tree}: not a folder", file=sys.stderr)
            return 2
        rekeyed: dict[str, str] = {}
        runs = list(run_dirs(tree))
        for run in runs:
            try:
                if args.measure:
                    measure(run, args.episodes_only, sizes)
                else:
                    slim(run, args.episodes_only, rekeyed, sizes)
            except (CheckpointError, PolicyFileError, OSError) as exc:
                print(f"error: {run}: {exc} (its network and checkpoints left as they were)", file=sys.stderr)
                return 1
        caches = 0 if args.measure else rekey_caches(tree, rekeyed)
        print(f"{tree}: {len(runs)} runs" + ("" if args.measure else f", {caches} cache files re-keyed"))
    verb = "would go" if args.measure else "went"
    for kind, (before, after) in sizes.items():
        print(f"{kind} {verb} from {before} to {after} bytes")
    before, after = sum(b for b, _ in sizes.values()), sum(a for _, a in sizes.values())
    print(f"slimmed parts {verb} from {before} to {after} bytes ({before - after} bytes less)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
