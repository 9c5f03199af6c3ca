"""Does a sound checkpoint fit the run it is resumed into? Checked before anything is restored.

A checkpoint can verify (its checksum matches) and still not fit: written by the project's own
`save_checkpoint` for a network of another size, or with a state field of the wrong type. Each
such problem is a `CheckpointCorrupt` naming it in one line, so a resume falls back to the
previous checkpoint instead of failing halfway through a restore with a traceback.
"""

from __future__ import annotations

import io
import random
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sitl_bridge.rl.learner.checkpoint import CheckpointCorrupt
from sitl_bridge.rl.learner.dqn import DQNAgent
from sitl_bridge.rl.learner.replay_store import ReplayStoreState

COUNTERS = ("episode", "global_step", "updates", "log_bytes")
RESTORE_ERRORS = (KeyError, TypeError, ValueError, IndexError, AttributeError, RuntimeError)
"""What reading a checkpoint's tensors or state into objects raises when they do not fit."""


def one_line(exc: BaseException) -> str:
    """An exception's message on one line (torch's size mismatches span several)."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 400 else text[:397] + "..."


def unfit(path: Path, exc: BaseException) -> CheckpointCorrupt:
    """The error for a checkpoint whose content does not fit what reads it."""
    what = f"missing {exc}" if isinstance(exc, KeyError) else one_line(exc)
    return CheckpointCorrupt(f"{path}: unusable content ({what})")


def check_fits(path: Path, tensors: dict[str, torch.Tensor], state: dict[str, Any], agent: DQNAgent,
               rng: np.random.Generator, prioritized_capacity: int | None) -> None:
    """Raise CheckpointCorrupt unless the trainer can restore every part of this checkpoint:
    counters, RNG states, replay state, network, optimizer and priority tensors (tried on
    throwaway objects; nothing of the trainer changes)."""
    try:
        _check_state(state, rng)
        for prefix, network in (("online.", agent.online), ("target.", agent.target)):
            _check_tensors(prefix, tensors, network.state_dict())
        _check_optimizer(tensors["optimizer"], agent.optimizer)
        if tensors["rng.torch"].dtype != torch.uint8 or tensors["rng.torch"].shape != torch.get_rng_state().shape:
            raise ValueError("rng.torch is not a torch RNG state")
        if prioritized_capacity is not None and "replay.priorities" in tensors:
            if tuple(tensors["replay.priorities"].shape) != (prioritized_capacity,):
                raise ValueError(f"replay.priorities holds {tuple(tensors['replay.priorities'].shape)} values, "
                                 f"the replay {prioritized_capacity}")
            float(tensors["replay.max_priority"])
    except RESTORE_ERRORS as exc:
        raise unfit(path, exc) from None


def _check_state(state: dict[str, Any], rng: np.random.Generator) -> None:
    for name in COUNTERS:
        value = state[name]
        if type(value) is not int or value < 0:
            raise TypeError(f"{name} is {value!r}, not a count")
    if isinstance(state["epsilon_max"], bool) or not isinstance(state["epsilon_max"], int | float):
        raise TypeError(f"epsilon_max is {state['epsilon_max']!r}, not a number")
    if not isinstance(state["recent_success"], list) or not all(type(s) is bool for s in state["recent_success"]):
        raise TypeError("recent_success is not a list of true/false")
    if type(state.get("evaluation_due", False)) is not bool:
        raise TypeError(f"evaluation_due is {state['evaluation_due']!r}, not true/false")
    replay = ReplayStoreState.from_json(state["replay"])
    if replay.total_rows != state["replay"]["total_rows"]:
        raise TypeError(f"replay.total_rows is {state['replay']['total_rows']!r}, not a count")
    version, internal, gauss = state["rng"]["python"]
    random.Random().setstate((version, tuple(internal), gauss))
    type(rng.bit_generator)().state = state["rng"]["numpy"]


def _check_tensors(prefix: str, tensors: dict[str, torch.Tensor], expected: dict[str, torch.Tensor]) -> None:
    mine = {k[len(prefix):]: v for k, v in tensors.items() if k.startswith(prefix)}
    if mine.keys() != expected.keys():
        raise ValueError(f"its {prefix}* tensors are not the network's (missing "
                         f"{sorted(expected.keys() - mine.keys())}, extra {sorted(mine.keys() - expected.keys())})")
    for name, tensor in expected.items():
        if mine[name].shape != tensor.shape or mine[name].dtype != tensor.dtype:
            raise ValueError(f"{prefix}{name} is {mine[name].dtype} {tuple(mine[name].shape)}, the network's "
                             f"{tensor.dtype} {tuple(tensor.shape)}")


def _check_optimizer(data: torch.Tensor, optimizer: torch.optim.Optimizer) -> None:
    saved = torch.load(io.BytesIO(data.numpy().tobytes()), weights_only=True)
    params = [p for group in optimizer.param_groups for p in group["params"]]
    if [len(g["params"]) for g in saved["param_groups"]] != [len(g["params"]) for g in optimizer.param_groups]:
        raise ValueError("the optimizer state is for another network")
    for index, values in saved["state"].items():
        for name, value in values.items():
            if isinstance(value, torch.Tensor) and value.dim() and value.shape != params[index].shape:
                raise ValueError(f"optimizer {name} of parameter {index} is {tuple(value.shape)}, the "
                                 f"parameter {tuple(params[index].shape)}")
