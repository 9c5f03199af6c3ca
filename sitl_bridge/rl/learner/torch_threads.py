"""How many CPU threads torch uses for the learner, set once where training starts.

Why few: the Q network is a small MLP (a few layers of 64-128 units, batches of 64-400), so one
update is about a hundred tensor operations of a few microseconds each. Splitting such an
operation over threads costs more in hand-over than it saves, and on a small machine (this
project's reference machine has 2 cores) the other cores are busy with the simulator, the
evaluation or another run of a sweep; torch's default of one thread per core then makes every
run slower. Inter-op parallelism (independent operators run side by side) has nothing to
overlap in an MLP, so its pool is kept at one thread too. With one intra-op thread the
reductions run in one fixed order, so a seed repeats bit for bit.
"""

from __future__ import annotations

import contextlib

import torch


def use_torch_threads(threads: int) -> None:
    """`threads` intra-op threads and one inter-op thread for this process's torch work."""
    torch.set_num_threads(threads)
    if torch.get_num_interop_threads() != 1:
        # Settable once per process, before the first inter-op work; a later call raises.
        with contextlib.suppress(RuntimeError):
            torch.set_num_interop_threads(1)
