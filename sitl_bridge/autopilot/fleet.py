"""`AutopilotFleet`: the autopilots of every vehicle of a `SimSession`, one class per kind.

The session composes world + simulation + HIL links + one fleet and never asks which kind it
runs: everything that differs between kinds (how autopilots start, when they are ready, how
they die, how an episode reset reboots them, how a setpoint is known to have arrived, what
their mode is, which ports they serve) is a method here. Kinds are listed by name in
`sitl_bridge.autopilot.registry`; adding one is a subclass plus a registry entry.

Life of a fleet inside a session (all calls from the session's controlling thread):

    pumps = fleet.start(links)           # start the autopilots; in-process ones return pumps
    fleet.connect(links, pumps)          # wait until each is connected to its HIL link
    fleet.wait_ready(lockstep)           # run the lockstep until observed ready (if it must)
    ... fleet.check()                    # [] while healthy, else AutopilotFault per problem
    fleet.reset(lockstep, reset_sim)     # next episode: in place, or a restart
    fleet.in_air_refusal(lockstep)       # resets_in_air kinds (px4): may the next episode
                                         # start in the air, the autopilots flying on?
    fleet.restart(lockstep)              # a supervisor's cure for a dead/frozen autopilot
    fleet.close()

Failsafe timeouts vs. speed factor: MAVSDK streams offboard setpoints and heartbeats in wall
time (20 Hz, 1 Hz) while autopilots measure their loss timeouts in simulated time, so at F x
real time the gap between two setpoints is F times longer in simulated time. Like PX4's rcS
with PX4_SIM_SPEED_FACTOR, the timeouts marked `wall` in `px4_params/*.params`
(COM_OF_LOSS_T, COM_DL_LOSS_T, COM_RC_LOSS_T) are multiplied by the speed factor (by 30 for
F = 0, which covers up to ~600x at MAVSDK's 20 Hz), capped at the file's maximum. The session
hands F to both autopilots, which apply it through their own parameter tables: PX4 via
`autopilot.px4` (PX4_PARAM_ environment, then read back and corrected over MAVLink, since
rcS rescales some of them itself) and the stub via `ParamTable(speed_factor=F)` (in-process,
or `sitl-bridge stub --speed-factor F`). Both read the same file, so they run with the same
configuration; `params=` overrides come last (unscaled).
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

from sitl_bridge.errors import ConfigError
from sitl_bridge.hil.errors import LinkClosed, LockstepTimeout
from sitl_bridge.ports import MAX_INSTANCE, VehiclePorts, vehicle_ports

if TYPE_CHECKING:
    from sitl_bridge.autopilot.in_air_reset import Estimate
    from sitl_bridge.hil import HilLink, Lockstep
    from sitl_bridge.world.schema import World

Pump = Callable[[], Any]
ServeUntil = Callable[[Callable[[], bool], float], None]
"""`serve_until(predicate, timeout_s)`: held, serve in-process autopilots until predicate()."""

PX4_SETPOINT_DELIVERY_S = 0.02
"""Wall seconds a held session waits for a process-based autopilot that reads its MAVLink
socket in wall time to take in new setpoints where their delivery cannot be observed (see
`deliver_setpoints`; on Linux `autopilot/px4/delivery.py` observes it)."""


class SessionError(RuntimeError):
    """The session could not start, or one of its parts (an autopilot among them) failed."""


class AutopilotFault(SessionError):
    """One vehicle's autopilot is dead or frozen: what a supervisor acts on (`restart()`).

    `reason`: `dead` (its process exited or its connection closed) or `frozen` (connected
    but not answering the lockstep in time)."""

    def __init__(self, message: str, *, vehicle: int, instance: int, reason: str) -> None:
        super().__init__(message)
        self.vehicle = vehicle
        self.instance = instance
        self.reason = reason


@dataclass(frozen=True)
class FleetConfig:
    """What every fleet is built from (the session's settings; a kind reads what it needs)."""

    world: World
    instances: tuple[int, ...]
    host: str = "127.0.0.1"
    speed_factor: float = 1.0
    params: Mapping[str, float] = field(default_factory=dict)
    """Extra autopilot parameters (PX4 names), applied after px4_params/."""
    ground_truth_estimate: bool = False
    """Estimate from ground truth instead of the sensors (kinds that support it)."""
    connect_timeout_s: float | None = 60.0
    """Wall seconds autopilots have to connect (None: forever)."""
    px4_bin: str | None = None
    px4_rootfs: str | None = None
    run_dir: Path | None = None
    """Where autopilot processes keep working directories and logs (None: a temp dir)."""
    api_telemetry: str = "full"
    """What the MAVLink API link streams to MAVSDK: "full" (the autopilot's usual onboard set)
    or "client" (only what `sitl_bridge.client` reads; kinds that support it: `px4`, `stub`)."""

    def __post_init__(self) -> None:
        if self.api_telemetry not in ("full", "client"):
            raise ConfigError(f"api_telemetry: expected 'full' or 'client', got {self.api_telemetry!r}")


@dataclass(frozen=True)
class VehicleSummary:
    """One vehicle as its autopilot reports it (the status line's mode and armed flag)."""

    mode: str
    armed: bool


class AutopilotFleet(ABC):
    """The autopilots of all vehicles of one session, of one kind (see module docstring)."""

    resets_in_place: ClassVar[bool] = True
    """`reset()` keeps the autopilots' MAVLink endpoints up: MAVSDK clients stay connected.
    False: a reset is a cold restart, and an env reconnects its clients (a new session)."""
    supports_ground_truth: ClassVar[bool] = False
    """`FleetConfig.ground_truth_estimate` is honoured (else it is a ConfigError)."""
    owns_autopilots: ClassVar[bool] = True
    """False: the autopilots are started by someone else (connect waits; no reset)."""
    resets_in_air: ClassVar[bool] = False
    """The next episode may start in the air with the autopilots flying on, not rebooted
    (`autopilot.in_air_reset.reset_in_air`, asking `in_air_refusal` before and after)."""
    places_in_air: ClassVar[bool] = False
    """`place_in_air` can start an episode with every vehicle hovering, no take-off flown."""
    last_instance: ClassVar[int] = MAX_INSTANCE
    """The highest vehicle instance an env of this kind claims (`autopilot.allocation`; px4:
    9, the last with an API port of its own)."""

    def __init__(self, config: FleetConfig) -> None:
        self.config = config
        self.instances = tuple(config.instances)

    @property
    def reads_hil_ground_truth(self) -> bool:
        """Whether these autopilots read the HIL_STATE_QUATERNION ground truth they may ask for
        (False: the HIL links do not send it, which saves both sides a message every step)."""
        return True

    # -- lifecycle ----------------------------------------------------------------------------
    @abstractmethod
    def start(self, links: Sequence[HilLink]) -> list[Pump]:
        """Start every autopilot (they connect to `links`, one per vehicle). Returns the
        lockstep pumps of in-process autopilots (empty for processes)."""

    def connect(self, links: Sequence[HilLink], pumps: Sequence[Pump] = ()) -> None:
        """Wait (wall time, `connect_timeout_s`) until every autopilot is connected to its
        link, running `pumps` meanwhile (in-process autopilots connect from them) and
        raising the first fault (a process that died while starting)."""
        timeout = self.config.connect_timeout_s
        deadline = None if timeout is None else time.monotonic() + timeout
        for link in links:
            while not link.accept(0.05):
                for pump in pumps:
                    pump()
                self.raise_faults()
                if deadline is not None and time.monotonic() > deadline:
                    raise SessionError(
                        f"vehicle {link.instance}: no autopilot connected to TCP {link.host}:{link.port} "
                        f"within {timeout:g} s")

    def wait_ready(self, lockstep: Lockstep) -> None:  # noqa: B027 - most kinds: ready on connect
        """Run `lockstep` until every autopilot is observed ready (default: connected is ready)."""

    @abstractmethod
    def close(self) -> None:
        """Stop every autopilot this fleet started and release its ports. Idempotent."""

    # -- health -------------------------------------------------------------------------------
    def check(self) -> list[AutopilotFault]:
        """What is wrong now: one `AutopilotFault` per dead or frozen autopilot this fleet
        can see on its own (a process that exited); [] when healthy."""
        return []

    def explain(self, error: BaseException) -> BaseException:
        """A lockstep/link failure (`LinkClosed`, `LockstepTimeout`) as what a supervisor
        acts on: the `AutopilotFault` of the vehicle it names (kinds with processes return
        the process's own report, e.g. its console tail, when that is what died); any other
        error unchanged."""
        if isinstance(error, LinkClosed) and error.instance in self.instances:
            return AutopilotFault(str(error), vehicle=self.instances.index(error.instance),
                                  instance=error.instance, reason="dead")
        if isinstance(error, LockstepTimeout):
            frozen = [i for i in error.instances if i in self.instances]
            if frozen:
                return AutopilotFault(str(error), vehicle=self.instances.index(frozen[0]),
                                      instance=frozen[0], reason="frozen")
        return error

    def raise_faults(self) -> None:
        """Raise the first fault `check()` reports."""
        faults = self.check()
        if faults:
            raise faults[0]

    # -- episodes -----------------------------------------------------------------------------
    def reset(self, lockstep: Lockstep, reset_simulation: Callable[[], None]) -> None:
        """Next episode, held: `reset_simulation()` (physics and sensors) and every autopilot
        rebooted. Default: a restart (`restart`); in-process kinds reboot in place."""
        self.restart(lockstep, reset_simulation)

    def place_in_air(self, lockstep: Lockstep, altitude_m: float) -> None:
        """Held, right after `reset`: every vehicle hovering `altitude_m` above its spawn, its
        autopilot in the state a take-off there ends in (armed, in the air, holding), without
        flying it. Kinds with `places_in_air` do (`autopilot.stub.in_air_start`)."""
        raise NotImplementedError(f"{type(self).__name__} does not place vehicles in the air")

    def in_air_refusal(self, lockstep: Lockstep) -> str:
        """Held: why the autopilots cannot fly on into the next episode ('' when they can:
        every one armed, in offboard, no failsafe, in the air, its estimate following the
        measured state). Kinds with `resets_in_air` answer; may advance simulated time a
        little to observe fresh reports."""
        return f"{type(self).__name__} does not reset in the air"

    def estimates(self, lockstep: Lockstep) -> list[Estimate]:
        """Held: what each vehicle's autopilot estimates of its own state now
        (`autopilot.in_air_reset` starts the next episode there); SessionError where one
        cannot tell. Kinds with `resets_in_air` answer; may advance simulated time a little to
        observe fresh reports."""
        raise NotImplementedError(f"{type(self).__name__} does not reset in the air")

    @abstractmethod
    def restart(self, lockstep: Lockstep, reset_simulation: Callable[[], None] | None = None) -> None:
        """Held: stop every autopilot, drop the links, `reset_simulation()` if given, start
        them again, reconnect and wait until ready (a cold boot). Also the cure for a fault."""

    # -- commands -----------------------------------------------------------------------------
    def deliver_setpoints(self, velocities_ned_m_s: Mapping[int, Sequence[float]],  # noqa: B027
                          serve_until: ServeUntil, timeout_s: float) -> None:
        """Held: return once the velocity setpoints just sent through MAVSDK (by vehicle
        instance) have reached their autopilots, so they act from the first step of the next
        run. Default: nothing can be observed, nothing to wait for."""

    # -- observation --------------------------------------------------------------------------
    @abstractmethod
    def summary(self, vehicle: int, link: HilLink) -> VehicleSummary:
        """Mode and armed flag of vehicle `vehicle` (index) as its autopilot reports it."""

    def ports(self, vehicle: int) -> VehiclePorts:
        """The ports of vehicle `vehicle` (index): HIL, MAVLink API, GCS."""
        return vehicle_ports(self.instances[vehicle])

    def describe(self) -> str:
        """What the banner of `sitl-bridge run` adds (e.g. what to start by hand); '' if nothing."""
        return ""


def link_summary(link: HilLink) -> VehicleSummary:
    """The armed flag of an autopilot's HIL heartbeat (else of its actuator answers); the
    mode is unknown on the HIL link ('-')."""
    armed = link.heartbeat.armed if link.heartbeat is not None else link.command.armed
    return VehicleSummary("-", bool(armed))


__all__ = [
    "PX4_SETPOINT_DELIVERY_S", "AutopilotFault", "AutopilotFleet", "FleetConfig", "Pump",
    "ServeUntil", "SessionError", "VehicleSummary", "link_summary",
]
