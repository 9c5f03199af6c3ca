"""The autopilot kinds, by name: the one list every `--autopilot` option, `SimSession` and
`make_env` take their choices from.

Each kind says what a session runs (`fleet`, an `AutopilotFleet` class, imported only when
used) and which env backend flies episodes on it (`env_backend`). Adding a kind is one fleet
class plus one `register(AutopilotKind(...))`; nothing else branches on the name.

| kind | session autopilots | env backend |
|---|---|---|
| `direct` | none: no sockets, the env steps physics and stub in-process | `DirectBackend` |
| `stub` | in-process stubs (`InProcessStubFleet`) | `SessionBackend` |
| `px4` | real PX4 SITL processes (`Px4SitlFleet`) | `SessionBackend` |
| `stub-process` | one `sitl-bridge stub` process per vehicle (`StubProcessFleet`) | none |
| `external` | started by someone else (`ExternalFleet`) | none (cannot be reset) |
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from sitl_bridge.errors import ConfigError

if TYPE_CHECKING:
    from sitl_bridge.autopilot.fleet import AutopilotFleet

SESSION_BACKEND = "sitl_bridge.envs.backends.session:SessionBackend"
"""The env backend of every kind with a session: episodes through SimSession and MAVSDK."""


def _load(target: Any) -> Any:
    """`target` itself, or the object a `"package.module:name"` string names."""
    if not isinstance(target, str):
        return target
    module, _, name = target.partition(":")
    return getattr(importlib.import_module(module), name)


@dataclass(frozen=True)
class AutopilotKind:
    """One autopilot kind (see module docstring)."""

    name: str
    help: str
    """One line for `--help`."""
    fleet: type[AutopilotFleet] | str | None
    """What `SimSession` runs (a class or `"module:Class"`); None: no session (`direct`)."""
    env_backend: Any = SESSION_BACKEND
    """The env backend class or `"module:Class"`, built as `Backend(world, options)`;
    None: envs cannot run on this kind."""
    ground_truth: bool | None = None
    """`estimator="ground_truth"` possible; None: as the fleet class says."""

    def fleet_class(self) -> type[AutopilotFleet]:
        """The fleet class (imported now); ConfigError for a kind without a session."""
        if self.fleet is None:
            raise ConfigError(f"autopilot: {self.name!r} runs without a simulator session; "
                              f"expected one of {', '.join(names(session=True))}")
        return _load(self.fleet)

    def backend_class(self) -> Any:
        """The env backend class (imported now); ValueError for a kind envs cannot use."""
        if self.env_backend is None:
            raise ValueError(f"autopilot must be one of {', '.join(names(env=True))}, got {self.name!r}")
        return _load(self.env_backend)

    @property
    def has_session(self) -> bool:
        return self.fleet is not None

    @property
    def has_env(self) -> bool:
        return self.env_backend is not None

    @property
    def supports_ground_truth(self) -> bool:
        if self.ground_truth is not None:
            return self.ground_truth
        return bool(self.fleet_class().supports_ground_truth)

    @property
    def resets_in_air(self) -> bool:
        """Its autopilots may fly on from one episode into the next (`AutopilotFleet.resets_in_air`)."""
        return self.fleet is not None and bool(self.fleet_class().resets_in_air)


_KINDS: dict[str, AutopilotKind] = {}


def register(kind: AutopilotKind, *, replace: bool = False) -> AutopilotKind:
    """Add a kind (at import time, or at run time: a plug-in, a test). ValueError if the name
    is taken, unless `replace`."""
    if kind.name in _KINDS and not replace:
        raise ValueError(f"autopilot kind {kind.name!r} is already registered")
    _KINDS[kind.name] = kind
    return kind


def unregister(name: str) -> None:
    """Remove a kind registered at run time (KeyError if unknown)."""
    del _KINDS[name]


def names(*, session: bool | None = None, env: bool | None = None) -> tuple[str, ...]:
    """Registered kind names in registration order; `session=True`: those `SimSession` (and
    `sitl-bridge run`) can run; `env=True`: those envs can run on."""
    return tuple(kind.name for kind in _KINDS.values()
                 if (session is None or kind.has_session == session)
                 and (env is None or kind.has_env == env))


def get(name: str) -> AutopilotKind:
    """The kind called `name`; ConfigError naming the choices otherwise."""
    kind = _KINDS.get(name)
    if kind is None:
        raise ConfigError(f"autopilot: expected one of {', '.join(names())}, got {name!r}")
    return kind


def session_kind(name: str) -> AutopilotKind:
    """The kind `name` if a `SimSession` can run it (ConfigError otherwise)."""
    kind = _KINDS.get(name)
    if kind is None or not kind.has_session:
        raise ConfigError(f"autopilot: expected one of {', '.join(names(session=True))}, got {name!r}")
    return kind


def env_kind(name: str) -> AutopilotKind:
    """The kind `name` if envs can run on it (ValueError otherwise)."""
    kind = _KINDS.get(name)
    if kind is None or not kind.has_env:
        raise ValueError(f"autopilot must be one of {', '.join(names(env=True))}, got {name!r}")
    return kind


register(AutopilotKind(
    "direct", "stub controller + physics in-process, no sockets (envs only; fastest)",
    fleet=None, env_backend="sitl_bridge.envs.backends.direct:DirectBackend", ground_truth=True))
register(AutopilotKind(
    "stub", "built-in PX4-compatible stub, in-process (the full protocol path)",
    fleet="sitl_bridge.autopilot.stub.fleet:InProcessStubFleet"))
register(AutopilotKind(
    "px4", "real PX4 SITL (--px4-bin / PX4_BIN)",
    fleet="sitl_bridge.autopilot.px4.fleet:Px4SitlFleet"))
register(AutopilotKind(
    "stub-process", "the stub, one `sitl-bridge stub -i N` process per vehicle",
    fleet="sitl_bridge.autopilot.stub.fleet:StubProcessFleet", env_backend=None))
register(AutopilotKind(
    "external", "autopilots started by hand, connecting to TCP 4560+i",
    fleet="sitl_bridge.autopilot.external:ExternalFleet", env_backend=None))


__all__ = [
    "SESSION_BACKEND", "AutopilotKind", "env_kind", "get", "names", "register", "session_kind", "unregister",
]
