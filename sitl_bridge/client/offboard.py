"""`OffboardClient`: offboard velocity flight over MAVSDK (the v4 native binding, sync API).

The same client flies the built-in stub and a real PX4: it only speaks MAVLink through MAVSDK,
on the API port of vehicle instance i (MAVSDK listens on `udpin://127.0.0.1:14540+i`).

Time: every wait is measured in *simulated* time when the client has a `clock` (the
`SimSession`). Waiting for an observation (health, ACK, altitude) advances the clock in small
chunks and checks after each; a velocity leg sets the setpoint and then advances exactly the
leg's duration. Nothing here sleeps to time a manoeuvre. Blocking MAVSDK calls run on a helper
thread while the caller advances the clock, because a held real PX4 is frozen in lockstep and
would never answer. Without a clock (a vehicle simulated elsewhere) waits poll in wall time and
timed legs are refused.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

import numpy as np
from mavsdk import Autopilot, ComponentType, Configuration, Mavsdk
from mavsdk.plugins.action import Action, ActionError
from mavsdk.plugins.offboard import Offboard, OffboardError, VelocityNedYaw
from mavsdk.plugins.param import Param, ParamError
from mavsdk.plugins.telemetry import FlightMode, LandedState, Telemetry

from sitl_bridge.autopilot.px4.delivery import own_threads, tag_mavsdk_io_thread
from sitl_bridge.client.actions import ACTION_DURATION_S, ACTION_SPEED_M_S, action_velocity_ned
from sitl_bridge.client.mavsdk_log import route_mavsdk_logs
from sitl_bridge.ports import API_CLIENT_BASE_PORT

log = logging.getLogger(__name__)


T = TypeVar("T")


class SimClock(Protocol):
    """What the client needs from the simulator: advance exactly `seconds` of simulated time,
    after making sure setpoints just sent have reached the autopilots (by vehicle instance)."""

    def run_for(self, seconds: float) -> None: ...

    def deliver_setpoints(self, velocities_ned_m_s: Mapping[int, Sequence[float]]) -> None: ...


class OffboardClientError(RuntimeError):
    """A MAVSDK request was refused or failed (the message names the request and the result)."""


class SimTimeoutError(TimeoutError):
    """An expected observation did not happen within its (simulated) time limit."""


@dataclass(frozen=True)
class VehicleStatus:
    """One telemetry snapshot as MAVSDK sees it."""

    flight_mode: str
    armed: bool
    in_air: bool
    position_ned_m: tuple[float, float, float]
    velocity_ned_m_s: tuple[float, float, float]


def wait_until(
    predicate: Callable[[], bool],
    *,
    clock: SimClock | None,
    timeout_s: float,
    what: str,
    poll_s: float = 0.04,
    min_wall_s: float = 0.0,
) -> None:
    """Return once `predicate()` is true; raise `SimTimeoutError` after `timeout_s`.

    With a clock, `timeout_s` and `poll_s` are simulated seconds and the clock is advanced by
    `poll_s` between checks (so the wait ends held); the timeout only fires once `min_wall_s`
    of wall time has passed as well (MAVSDK retries commands on a wall-clock timer, which at
    a high speed factor spans many simulated seconds). Without a clock they are wall seconds.
    """
    if predicate():
        return
    if clock is None:
        deadline = time.monotonic() + timeout_s
        while not predicate():
            if time.monotonic() > deadline:
                raise SimTimeoutError(f"{what}: not observed within {timeout_s:g} s (wall time)")
            time.sleep(min(poll_s, 0.01))  # polling an observation, not timing a manoeuvre
        return
    elapsed = 0.0
    wall_deadline = time.monotonic() + min_wall_s
    while not predicate():
        if elapsed >= timeout_s - 1e-9 and time.monotonic() >= wall_deadline:
            raise SimTimeoutError(f"{what}: not observed within {timeout_s:g} s of simulated time")
        clock.run_for(poll_s)
        elapsed += poll_s


class OffboardClient:
    """MAVSDK client for one vehicle instance: health, arm, takeoff, offboard velocity, land.

    Use as a context manager (or call `close()`): it owns a `Mavsdk` instance, its UDP port
    and a helper thread. Several clients (one per vehicle) can share one clock; see
    `sitl_bridge.client.fleet.Fleet` to fly them together.
    """

    COMMAND_POLL_S = 0.02
    """Simulated seconds advanced between checks while a MAVSDK request is in flight."""

    SETTLED_VERTICAL_SPEED_M_S = 0.3
    """Below this climb/sink rate a vehicle in HOLD after takeoff counts as hovering."""

    COMMAND_MIN_WALL_S = 5.0
    """A request is given at least this much wall time: MAVSDK resends a command 3 times
    0.5 s (wall) apart before reporting a timeout itself, whatever the speed factor. The
    discovery of the autopilot when connecting gets the same floor."""

    def __init__(
        self,
        instance: int,
        *,
        clock: SimClock | None = None,
        host: str = "127.0.0.1",
        base_port: int = API_CLIENT_BASE_PORT,
        url: str | None = None,
    ) -> None:
        self.instance = instance
        self.clock = clock
        self.url = url or f"udpin://{host}:{base_port + instance}"
        self._mavsdk: Mavsdk | None = None
        self._config: Configuration | None = None
        self._system: Any = None
        self._action: Action | None = None
        self._offboard: Offboard | None = None
        self._telemetry: Telemetry | None = None
        self._param: Param | None = None
        self._executor: ThreadPoolExecutor | None = None
        self._yaw_deg = 0.0
        self._velocity_ned_m_s = np.zeros(3)

    # -- lifecycle --------------------------------------------------------------------
    def connect(self, timeout_s: float = 30.0) -> OffboardClient:
        """Listen on the API port and wait until MAVSDK has discovered the autopilot and its
        telemetry has seen a HEARTBEAT. On failure everything opened so far is released."""
        try:
            return self._connect(timeout_s)
        except BaseException:
            self.close()
            raise

    def _connect(self, timeout_s: float) -> OffboardClient:
        route_mavsdk_logs()
        self._config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
        threads = own_threads()
        self._mavsdk = Mavsdk(self._config)
        # registered, so a held session can see it go idle after sending (`wait_delivered`)
        tag_mavsdk_io_thread(threads)
        self._mavsdk.add_any_connection_with_handle(self.url)
        self._executor = ThreadPoolExecutor(1, thread_name_prefix=f"mavsdk-{self.instance}")
        found: list[Any] = []
        ready = threading.Event()

        def on_autopilot(system: Any) -> None:
            found.append(system)
            ready.set()

        handle = self._mavsdk.first_autopilot_async(-1.0, on_autopilot)
        try:
            # MAVSDK discovers the autopilot in its own threads, in wall time: on a busy machine
            # at full speed the timeout's simulated seconds can pass before they get a core
            wait_until(ready.is_set, clock=self.clock, timeout_s=timeout_s,
                       what=f"vehicle {self.instance}: autopilot heartbeat on {self.url}",
                       min_wall_s=self.COMMAND_MIN_WALL_S)
        finally:
            self._mavsdk.cancel_first_autopilot(handle)
        if not found or found[0] is None:
            raise OffboardClientError(f"vehicle {self.instance}: no autopilot on {self.url}")
        self._system = found[0]
        self._action = Action(self._system)
        self._offboard = Offboard(self._system)
        self._telemetry = Telemetry(self._system)
        self._param = Param(self._system)
        self._wait_first_heartbeat(timeout_s)
        return self

    def _wait_first_heartbeat(self, timeout_s: float) -> None:
        """Telemetry caches armed/mode from HEARTBEATs that arrive after the plugin exists;
        wait for one so that `armed()` and friends are valid when connect() returns."""
        telemetry = self.telemetry
        seen = threading.Event()
        handle = telemetry.subscribe_armed(lambda _armed, _ud: seen.set())
        try:
            self.wait_until(seen.is_set, "first heartbeat after connecting", timeout_s)
        finally:
            telemetry.unsubscribe_armed(handle)

    def close(self) -> None:
        """Release MAVSDK (its threads and UDP port) and the helper thread. Idempotent."""
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None
        if self._mavsdk is not None:
            self._mavsdk.destroy()  # also destroys the system and its plugins
            self._mavsdk = None
        if self._config is not None:
            self._config.destroy()
            self._config = None
        self._system = self._action = self._offboard = self._telemetry = self._param = None

    def __enter__(self) -> OffboardClient:
        if self._mavsdk is None:
            self.connect()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # -- plumbing ---------------------------------------------------------------------
    def _require(self, plugin: T | None) -> T:
        if plugin is None:
            raise OffboardClientError(f"vehicle {self.instance}: not connected (call connect())")
        return plugin

    def submit(self, fn: Callable[..., T], *args: Any) -> Future[T]:
        """Run a blocking MAVSDK call on the helper thread (see `finish`)."""
        if self._executor is None:
            raise OffboardClientError(f"vehicle {self.instance}: not connected (call connect())")
        return self._executor.submit(fn, *args)

    def finish(self, future: Future[T], what: str, timeout_s: float = 10.0) -> T:
        """Advance the clock until `future` is done; its MAVSDK error becomes OffboardClientError."""
        wait_until(future.done, clock=self.clock, timeout_s=timeout_s,
                   what=f"vehicle {self.instance}: {what}", poll_s=self.COMMAND_POLL_S,
                   min_wall_s=self.COMMAND_MIN_WALL_S)
        try:
            return future.result()
        except (ActionError, OffboardError, ParamError) as exc:
            raise OffboardClientError(f"vehicle {self.instance}: {what} failed: {exc.result.name}") from exc

    def _call(self, fn: Callable[..., T], *args: Any, what: str) -> T:
        return self.finish(self.submit(fn, *args), what)

    def wait_until(self, predicate: Callable[[], bool], what: str, timeout_s: float) -> None:
        """`wait_until` with this client's clock, naming the vehicle in errors."""
        wait_until(predicate, clock=self.clock, timeout_s=timeout_s,
                   what=f"vehicle {self.instance}: {what}")

    @property
    def action(self) -> Action:
        """MAVSDK's Action plugin for this vehicle (for requests this class does not wrap)."""
        return self._require(self._action)

    @property
    def telemetry(self) -> Telemetry:
        """MAVSDK's Telemetry plugin for this vehicle."""
        return self._require(self._telemetry)

    # -- telemetry --------------------------------------------------------------------
    def autopilot_type(self) -> str:
        """'PX4', 'ARDUPILOT', 'GENERIC' or 'UNKNOWN', from the autopilot's HEARTBEAT."""
        return Autopilot(self._require(self._system).autopilot_type()).name

    def health(self) -> dict[str, bool]:
        """MAVSDK's health flags (`is_global_position_ok`, `is_armable`, ...)."""
        health = self.telemetry.health()
        return {name: bool(value) for name, value in vars(health).items()}

    def is_healthy(self) -> bool:
        """True when every MAVSDK health flag is true."""
        return all(self.health().values())

    def flight_mode(self) -> str:
        """Flight mode name as MAVSDK decodes it ('HOLD', 'OFFBOARD', 'LAND', ...)."""
        return FlightMode(self.telemetry.flight_mode()).name

    def armed(self) -> bool:
        return bool(self.telemetry.armed())

    def in_air(self) -> bool:
        return bool(self.telemetry.in_air())

    def landed_state(self) -> str:
        return LandedState(self.telemetry.landed_state()).name

    def position_ned_m(self) -> np.ndarray:
        """Local position (LOCAL_POSITION_NED), metres north/east/down from the origin."""
        pos = self.telemetry.position_velocity_ned().position
        return np.array([pos.north_m, pos.east_m, pos.down_m])

    def velocity_ned_m_s(self) -> np.ndarray:
        vel = self.telemetry.position_velocity_ned().velocity
        return np.array([vel.north_m_s, vel.east_m_s, vel.down_m_s])

    def relative_altitude_m(self) -> float:
        """Height above home (GLOBAL_POSITION_INT relative_alt)."""
        return float(self.telemetry.position().relative_altitude_m)

    def status(self) -> VehicleStatus:
        pv = self.telemetry.position_velocity_ned()
        return VehicleStatus(
            flight_mode=self.flight_mode(),
            armed=self.armed(),
            in_air=self.in_air(),
            position_ned_m=(pv.position.north_m, pv.position.east_m, pv.position.down_m),
            velocity_ned_m_s=(pv.velocity.north_m_s, pv.velocity.east_m_s, pv.velocity.down_m_s),
        )

    # -- parameters -------------------------------------------------------------------
    def get_param_float(self, name: str) -> float:
        param = self._require(self._param)
        return float(self._call(param.get_param_float, name, what=f"read {name}"))

    def set_param_float(self, name: str, value: float) -> None:
        param = self._require(self._param)
        self._call(param.set_param_float, name, float(value), what=f"set {name}")

    def get_param_int(self, name: str) -> int:
        param = self._require(self._param)
        return int(self._call(param.get_param_int, name, what=f"read {name}"))

    def set_param_int(self, name: str, value: int) -> None:
        param = self._require(self._param)
        self._call(param.set_param_int, name, int(value), what=f"set {name}")

    # -- flight: each step is "request" (no wait) + "wait"; the plain method does both ----
    def wait_healthy(self, timeout_s: float = 60.0) -> None:
        """Wait until MAVSDK reports every health flag true (position, home, armable, ...)."""
        self.wait_until(self.is_healthy, "all health flags true", timeout_s)

    def arm(self) -> None:
        """Arm and wait for the ACK (`armed()` follows with the next HEARTBEAT)."""
        self._call(self.action.arm, what="arm")

    def disarm(self) -> None:
        self._call(self.action.disarm, what="disarm")

    def request_takeoff(self, altitude_m: float | None = None) -> Future[Any]:
        """Set MIS_TAKEOFF_ALT (when given) and send the takeoff command; finish() the result."""
        action = self.action

        def takeoff() -> Any:
            if altitude_m is not None:
                action.set_takeoff_altitude(float(altitude_m))
            return action.takeoff()

        return self.submit(takeoff)

    def takeoff_done(self, altitude_m: float, tolerance_m: float = 0.3) -> bool:
        """Takeoff is over: in the air, in HOLD (PX4 loiters once near the takeoff altitude),
        within `tolerance_m` of `altitude_m` above home and no longer climbing."""
        return (
            self.in_air()
            and self.flight_mode() == "HOLD"
            and abs(self.relative_altitude_m() - altitude_m) <= tolerance_m
            and abs(float(self.velocity_ned_m_s()[2])) < self.SETTLED_VERTICAL_SPEED_M_S
        )

    def takeoff(self, altitude_m: float | None = None, *, timeout_s: float = 30.0,
                tolerance_m: float = 0.3) -> float:
        """Take off and wait (simulated time) until hovering at the takeoff altitude.

        Without `altitude_m` the vehicle's MIS_TAKEOFF_ALT is used. Returns the altitude above
        home that telemetry reports. (PX4 switches to HOLD some decimetres early and climbs
        the rest slowly; the wait covers that.)
        """
        self.finish(self.request_takeoff(altitude_m), "takeoff")
        target = float(altitude_m) if altitude_m is not None else self.get_param_float("MIS_TAKEOFF_ALT")
        self.wait_until(lambda: self.takeoff_done(target, tolerance_m),
                        f"hovering at {target:g} +- {tolerance_m:g} m after takeoff", timeout_s)
        return self.relative_altitude_m()

    def set_velocity_ned(self, velocity_ned_m_s: Sequence[float] | np.ndarray,
                         yaw_deg: float | None = None) -> None:
        """Send a velocity setpoint now; MAVSDK repeats it at 20 Hz until the next one.

        The yaw is held at the heading recorded when offboard started unless given.
        """
        north, east, down = (float(v) for v in velocity_ned_m_s)
        if yaw_deg is not None:
            self._yaw_deg = float(yaw_deg)
        offboard = self._require(self._offboard)
        try:
            offboard.set_velocity_ned(VelocityNedYaw(north, east, down, self._yaw_deg))
        except OffboardError as exc:
            raise OffboardClientError(f"vehicle {self.instance}: velocity setpoint failed: {exc.result.name}") from exc
        self._velocity_ned_m_s = np.array([north, east, down])

    @property
    def commanded_velocity_ned_m_s(self) -> np.ndarray:
        """The last velocity setpoint sent (NED, m/s)."""
        return self._velocity_ned_m_s.copy()

    def commanded_setpoint_ned(self, *, with_yaw: bool = False) -> np.ndarray:
        """The last velocity setpoint sent (NED, m/s), with its heading (NED yaw, rad) appended
        when `with_yaw` (what a delivery check compares)."""
        if not with_yaw:
            return self.commanded_velocity_ned_m_s
        return np.append(self._velocity_ned_m_s, math.radians(self._yaw_deg))

    def request_offboard(self, yaw_deg: float | None = None) -> Future[Any]:
        """Send a zero-velocity setpoint (required before start), then request OFFBOARD.
        The setpoints hold heading `yaw_deg` (NED, degrees from north); without it, the
        heading telemetry reports now (read in wall time: where it matters which report that
        was, as in an env's episodes, give the heading)."""
        if yaw_deg is None:
            heading = float(self.telemetry.heading().heading_deg)
            yaw_deg = heading if math.isfinite(heading) else 0.0
        self._yaw_deg = float(yaw_deg)
        self.set_velocity_ned((0.0, 0.0, 0.0))
        return self.submit(self._require(self._offboard).start)

    def start_offboard(self, timeout_s: float = 5.0, yaw_deg: float | None = None) -> None:
        """Enter OFFBOARD holding position (zero velocity) at heading `yaw_deg` (see
        `request_offboard`) and wait until the mode is reported."""
        self.finish(self.request_offboard(yaw_deg), "start offboard")
        self.wait_until(lambda: self.flight_mode() == "OFFBOARD", "flight mode OFFBOARD", timeout_s)

    def fly_velocity_ned(self, velocity_ned_m_s: Sequence[float] | np.ndarray,
                         duration_s: float) -> None:
        """Fly a velocity setpoint for exactly `duration_s` simulated seconds, then stay held."""
        if self.clock is None:
            raise OffboardClientError("timed legs need a simulation clock (SimSession)")
        self.set_velocity_ned(velocity_ned_m_s)
        self.clock.deliver_setpoints({self.instance: self._velocity_ned_m_s})
        self.clock.run_for(duration_s)

    def fly_action(self, action: int, *, goal_ned_m: Sequence[float] | None = None,
                   speed_m_s: float = ACTION_SPEED_M_S,
                   duration_s: float = ACTION_DURATION_S) -> np.ndarray:
        """Fly one thesis action (0..7); returns the NED velocity that was commanded."""
        velocity = action_velocity_ned(action, position_ned_m=self.position_ned_m(),
                                       goal_ned_m=goal_ned_m, speed_m_s=speed_m_s)
        self.fly_velocity_ned(velocity, duration_s)
        return velocity

    def request_hold(self) -> Future[Any]:
        """Leave offboard (MAVSDK stops its setpoint stream) and switch to HOLD."""
        offboard = self._require(self._offboard)
        action = self.action

        def hold() -> Any:
            return offboard.stop() if offboard.is_active() else action.hold()

        return self.submit(hold)

    def hold(self, timeout_s: float = 5.0) -> None:
        """Switch to HOLD and wait until the mode is reported."""
        self.finish(self.request_hold(), "hold")
        self.wait_until(lambda: self.flight_mode() == "HOLD", "flight mode HOLD", timeout_s)

    def request_land(self) -> Future[Any]:
        return self.submit(self.action.land)

    def landed_and_disarmed(self) -> bool:
        return not self.in_air() and not self.armed()

    def land(self, timeout_s: float = 60.0) -> None:
        """Land and wait (simulated time) until on the ground and disarmed (auto-disarm)."""
        self.finish(self.request_land(), "land")
        self.wait_until(self.landed_and_disarmed, "landed and disarmed", timeout_s)
