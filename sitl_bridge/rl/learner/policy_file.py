"""Policy files: a trained network alone (`policy.safetensors`), no optimizer, replay or RNG state.

The network's shape says which algorithm made it (`algorithm`: absent or dqn for the project's
Q network, ppo/sac/td3 for a Stable-Baselines3 policy, `rl/learner/sb3_models.py`);
`build_network` is the one place that turns a shape and tensors into a network, for every reader.

A training checkpoint carries everything a resume needs (optimizer, replay priorities, RNG
states) and weighs megabytes; the greedy policy needs only the online network (tens of KB). A
policy file is a safetensors file whose tensors are the network's `state_dict` (normalizer
statistics included, they are buffers of the network) and whose metadata holds the network's
shape (enough to rebuild it), the training episode behind it, and a SHA-256 over all of it.

It also holds the Q values the network gave, when it was exported from its checkpoint, on
`PROBE_COUNT` fixed probe observations: `read_policy` rebuilds the network and checks that it
still answers them the same, so a file that loads but computes something else is refused.
"""

from __future__ import annotations

import hashlib
import json
import struct
from pathlib import Path
from typing import Any

import safetensors.torch
import torch
from torch import nn

from sitl_bridge.rl.learner.dqn import NetworkShape, QNetwork

FORMAT = "sitl_bridge.policy/1"
POLICY_FILE = "policy.safetensors"
"""In a run directory: the policy-only export of its best network (`sitl-bridge export`)."""
PROBE_COUNT = 256
PROBE_SEED = 7_302_025
PROBE_TENSOR = "probe.q"
"""The Q values of the probe observations, as the checkpoint's network computed them."""
ONLINE = "online."
"""Prefix of the network's tensors in a training checkpoint (what `resolve_checkpoint` returns)."""


class PolicyFileError(RuntimeError):
    """A policy file is damaged, truncated, not a policy file, or computes other Q values."""


def probe_observations(obs_dim: int) -> torch.Tensor:
    """`PROBE_COUNT` fixed observations (spread wider than unit scale, so every PReLU's negative
    side and the normalizer's clipping are exercised too)."""
    generator = torch.Generator().manual_seed(PROBE_SEED)
    return torch.randn(PROBE_COUNT, obs_dim, generator=generator) * 3.0


def network_digest(tensors: dict[str, torch.Tensor], shape: dict[str, Any]) -> str:
    """SHA-256 of a network: its shape and every tensor's name, dtype, dimensions and bytes.
    The same for a training checkpoint and its policy export (keys without the `online.` prefix)."""
    sha = hashlib.sha256(json.dumps(shape, sort_keys=True).encode())
    for name in sorted(tensors):
        tensor = tensors[name].detach().cpu().contiguous()
        sha.update(f"{name}|{tensor.dtype}|{tuple(tensor.shape)}|".encode())
        sha.update(tensor.view(-1).view(torch.uint8).numpy().tobytes() if tensor.numel() else b"")
    return sha.hexdigest()


def online_tensors(tensors: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The online network's tensors of a checkpoint, without their `online.` prefix."""
    return {k[len(ONLINE):]: v for k, v in tensors.items() if k.startswith(ONLINE)}


def network_algorithm(shape: dict[str, Any]) -> str:
    """The algorithm a saved network shape belongs to (shapes written before SB3 runs: dqn)."""
    return str(shape.get("algorithm", "dqn"))


def build_network(shape: dict[str, Any], network: dict[str, torch.Tensor]) -> nn.Module:
    """The network of `shape` holding `network`'s weights, in eval mode: a QNetwork, or for an
    SB3 algorithm's shape its policy (`SB3Network`: forward gives the deterministic action's
    scores). Raises RuntimeError/TypeError/KeyError when the tensors do not fit the shape."""
    if network_algorithm(shape) != "dqn":
        from sitl_bridge.rl.learner.sb3_models import SB3Network

        return SB3Network.build(shape, network)
    model = QNetwork(NetworkShape(**shape))
    model.load_state_dict(network)
    model.eval()
    return model


def probe_q_values(model: nn.Module) -> torch.Tensor:
    """The network's outputs on the probe observations (Q values, or an SB3 policy's scores)."""
    with torch.no_grad():
        return model(probe_observations(model.shape.obs_dim)).to(torch.float32)


def policy_bytes(network: dict[str, torch.Tensor], shape: dict[str, Any], *, episode: int,
                 exported_from: str, probe_q: torch.Tensor) -> bytes:
    """The policy file's bytes for `network` (unprefixed state_dict) of `shape`."""
    tensors = {k: v.detach().cpu().contiguous().clone() for k, v in network.items()}
    tensors[PROBE_TENSOR] = probe_q.detach().cpu().contiguous().clone()
    metadata = {"format": FORMAT, "network": json.dumps(shape, sort_keys=True), "episode": str(int(episode)),
                "exported_from": exported_from, "algorithm": network_algorithm(shape)}
    metadata["sha256"] = _file_digest(tensors, metadata)
    return safetensors.torch.save(tensors, metadata=metadata)


def _file_digest(tensors: dict[str, torch.Tensor], metadata: dict[str, str]) -> str:
    described = {k: v for k, v in metadata.items() if k != "sha256"}
    return network_digest(tensors, described)


def _header(data: bytes) -> dict[str, Any]:
    if len(data) < 8:
        raise PolicyFileError("file is shorter than a safetensors header")
    (length,) = struct.unpack("<Q", data[:8])
    if length > len(data) - 8:
        raise PolicyFileError("file is truncated (header runs past the end)")
    try:
        header = json.loads(data[8:8 + length])
    except ValueError:
        raise PolicyFileError("header is not valid JSON") from None
    if not isinstance(header, dict):
        raise PolicyFileError("header is not a mapping")
    return header


def is_policy_file(path: str | Path) -> bool:
    """Whether `path` is a file whose safetensors header says it is a policy file."""
    try:
        with open(path, "rb") as handle:
            head = handle.read(8)
            if len(head) < 8:
                return False
            (length,) = struct.unpack("<Q", head)
            header = _header(head + handle.read(min(length, 1 << 26)))
    except (OSError, PolicyFileError):
        return False
    return (header.get("__metadata__") or {}).get("format") == FORMAT


def parse_policy(data: bytes, source: str = "policy") -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Verify a policy file's bytes (format, length, checksum, probe Q values) and return the
    network's tensors (with the `online.` prefix of a checkpoint) and its state (`network`,
    `episode`, `policy_only`), the shape `resolve_checkpoint` gives for a checkpoint."""
    try:
        header = _header(data)
        metadata = header.get("__metadata__") or {}
        if metadata.get("format") != FORMAT:
            raise PolicyFileError(f"not a sitl-bridge policy file (format {metadata.get('format')!r})")
        end = max((v["data_offsets"][1] for k, v in header.items() if k != "__metadata__"), default=0)
        if 8 + struct.unpack("<Q", data[:8])[0] + end != len(data):
            raise PolicyFileError("file is truncated")
        try:
            tensors = safetensors.torch.load(data)
        except Exception as exc:  # safetensors raises its own error types for damaged files
            raise PolicyFileError(f"unreadable safetensors data ({exc})") from None
        if _file_digest(tensors, metadata) != metadata.get("sha256"):
            raise PolicyFileError("checksum mismatch (file damaged)")
        shape = json.loads(metadata["network"])
        # files written before the field: their network is what the shape says (no algorithm: dqn)
        if metadata.get("algorithm", network_algorithm(shape)) != network_algorithm(shape):
            raise PolicyFileError(f"says it holds a {metadata['algorithm']} network, but its shape is a "
                                  f"{network_algorithm(shape)} one")
        expected = tensors.pop(PROBE_TENSOR, None)
        if expected is None:
            raise PolicyFileError(f"no {PROBE_TENSOR} tensor to check the network against")
        try:
            model = build_network(shape, tensors)
        except (RuntimeError, TypeError, KeyError, ValueError) as exc:
            raise PolicyFileError(f"the tensors do not make the network it describes ({exc})") from None
        if not torch.allclose(probe_q_values(model), expected, rtol=1e-5, atol=1e-6):
            raise PolicyFileError("the network's Q values on the probe observations differ from the exported ones")
    except PolicyFileError as exc:
        raise PolicyFileError(f"{source}: {exc}") from None
    state = {"network": shape, "episode": int(metadata["episode"]), "policy_only": True,
             "algorithm": network_algorithm(shape),
             "exported_from": metadata.get("exported_from", "")}
    return {ONLINE + k: v for k, v in tensors.items()}, state


def read_policy(path: str | Path) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Read and verify a policy file (see `parse_policy`); raises PolicyFileError naming it."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise PolicyFileError(f"{path}: cannot read ({exc.strerror})") from None
    return parse_policy(data, str(path))
