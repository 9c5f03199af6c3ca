"""`Px4Fleet`: the PX4 processes of all vehicles of a lockstep, started, connected, made
ready, restarted (or reset in place) between episodes, stopped; `Px4SitlFleet`: the same as
a session's `px4` autopilot kind."""

from __future__ import annotations

import logging
import math
import shutil
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from sitl_bridge import mavlink
from sitl_bridge.autopilot.fleet import (
    PX4_SETPOINT_DELIVERY_S,
    AutopilotFault,
    AutopilotFleet,
    FleetConfig,
    ServeUntil,
    SessionError,
    VehicleSummary,
    link_summary,
)
from sitl_bridge.autopilot.in_air_reset import Estimate
from sitl_bridge.autopilot.px4.delivery import wait_delivered
from sitl_bridge.autopilot.px4.in_air import IN_AIR_LIMITS, InAirLimits, describe
from sitl_bridge.autopilot.px4.in_air import refusal as in_air_refusal
from sitl_bridge.autopilot.px4.observer import Px4Observation
from sitl_bridge.autopilot.px4.params import load_param_overrides
from sitl_bridge.autopilot.px4.process import Px4Autopilot, Px4Config, Px4Died, Px4Error
from sitl_bridge.autopilot.px4.quiescence import Px4Quiescence
from sitl_bridge.autopilot.px4.temp_dirs import make_temp_run_dir
from sitl_bridge.errors import ConfigError
from sitl_bridge.hil.errors import HilError
from sitl_bridge.ports import (
    PX4_LAST_OWN_API_INSTANCE,
    PX4_SHARED_API_PORT,
    VehiclePorts,
    api_bind_port,
    vehicle_ports,
)

log = logging.getLogger(__name__)

IN_AIR_FRESH_S = 1.0
"""`in_air_refusal` trusts PX4's reports read within this much simulated time."""
IN_AIR_OBSERVE_S = 0.2
"""... else it runs this long first (PX4 streams HEARTBEAT, EXTENDED_SYS_STATE at 10 Hz and
LOCAL_POSITION_NED at 50 Hz on the GCS link: px4_params/px4-rc.mavlink)."""


class Px4Fleet:
    """PX4 processes for vehicles 0..n-1 of a lockstep (instances `instance_base + i`):
    start, connect to the links, wait until ready, restart between episodes, stop.

    `lockstep` is a `sitl_bridge.hil.Lockstep` whose links are the vehicles' `HilLink`s.
    """

    def __init__(self, config: Px4Config, instances: Sequence[int]) -> None:
        self.autopilots = [Px4Autopilot(config, instance) for instance in instances]
        self.last_ready_wall_s = 0.0
        # true NED position minus PX4's local estimate, when each became ready
        self._origin_offsets: list[tuple[float, float, float] | None] = [None] * len(self.autopilots)
        self._polled_at_step = -(2**62)  # lockstep step of the last in_air_refusal's reading
        self.quiescence = Px4Quiescence()
        self._quiet_lockstep: Any = None  # the lockstep `wait_quiet` observes

    def start(self) -> None:
        for autopilot in self.autopilots:
            autopilot.start()

    def stop(self) -> None:
        for autopilot in self.autopilots:
            autopilot.stop()
        self.quiescence.forget()

    def wait_quiet(self, lockstep: Any) -> None:
        """`Lockstep.after_step` observer: wait until every PX4 answering the lockstep has done
        the work of the step (`quiescence.py`), so the next step finds it in the same state
        whatever the machine's load. PX4s still booting (no answer yet) are not waited for."""
        pids = [autopilot.pid for autopilot, link in zip(self.autopilots, lockstep.links, strict=True)
                if link.actuators_flowing and autopilot.pid is not None]
        if pids:
            self.quiescence.wait(pids)

    def check_alive(self) -> None:
        for autopilot in self.autopilots:
            autopilot.check_alive()

    def explain(self, error: BaseException, wait_s: float = 2.0) -> BaseException:
        """Turn a link failure (LinkClosed, LockstepTimeout) into `Px4Died` with the console
        tail when a PX4 process is what died (waiting up to `wait_s` for it to exit);
        otherwise return `error` unchanged. Use as `raise fleet.explain(exc) from exc`."""
        deadline = time.monotonic() + wait_s
        while True:
            for autopilot in self.autopilots:
                if autopilot.returncode is not None:
                    try:
                        autopilot.check_alive()
                    except Px4Died as died:
                        return died
            if time.monotonic() > deadline:
                return error
            time.sleep(0.02)

    def connect(self, links: Sequence[Any], timeout_s: float = 30.0) -> None:
        """Wait until every PX4 connected to its link (checking that none died)."""
        deadline = time.monotonic() + timeout_s
        for autopilot, link in zip(self.autopilots, links, strict=True):
            while not link.accept(0.05):
                autopilot.check_alive()
                if time.monotonic() > deadline:
                    raise Px4Error(
                        f"PX4 instance {autopilot.instance} did not connect to TCP {link.port} "
                        f"within {timeout_s} s; last output:\n{autopilot.tail()}"
                    )

    def wait_ready(self, lockstep: Any, *, timeout_s: float = 120.0, max_sim_s: float = 300.0) -> float:
        """Run the lockstep until every PX4 is observed ready; returns the wall seconds it
        took. Raises Px4Died or Px4Error (with console tails) on failure."""
        start = time.monotonic()
        deadline = start + timeout_s
        if self._quiet_lockstep is not lockstep:  # once per lockstep, restarts included
            lockstep.after_step.append(lambda: self.wait_quiet(lockstep))
            self._quiet_lockstep = lockstep

        def tails() -> str:
            return "\n".join(f"--- PX4 instance {a.instance} ({a.observation}):\n{a.tail(15)}"
                             for a in self.autopilots)

        def all_ready() -> bool:
            self.check_alive()
            if time.monotonic() > deadline:
                raise Px4Error(f"PX4 not ready after {timeout_s} s wall:\n{tails()}")
            return all(a.ready and a.observation.position_ned_m is not None for a in self.autopilots)

        try:
            ready = lockstep.run_until(all_ready, max_seconds=max_sim_s, check_every_s=0.2)
        except HilError as exc:
            raise self.explain(exc) from exc
        if not ready:
            raise Px4Error(f"PX4 not ready after {max_sim_s} s of simulated time:\n{tails()}")
        for index, autopilot in enumerate(self.autopilots):
            self._origin_offsets[index] = self._offset(lockstep, index, autopilot.observation)
        self.last_ready_wall_s = time.monotonic() - start
        return self.last_ready_wall_s

    @staticmethod
    def _offset(lockstep: Any, index: int, obs: Px4Observation) -> tuple[float, float, float]:
        # what PX4's sensors measure: the truth plus the suite's measured position offset
        true = lockstep.sim.state(index).position_ned_m
        shift = lockstep.sensors[index].position_offset_ned_m
        estimate = obs.position_ned_m or (0.0, 0.0, 0.0)
        return tuple(float(t) + o - e for t, o, e in zip(true, shift, estimate, strict=True))  # type: ignore[return-value]

    def estimate_error_m(self, lockstep: Any, index: int) -> float:
        """Distance between PX4's position estimate and the position its sensors measure (the
        truth plus their measured position offset, see `SensorSuite`), in PX4's local frame."""
        obs = self.autopilots[index].observation
        origin = self._origin_offsets[index]
        if obs.position_ned_m is None or origin is None:
            return float("inf")
        offset = self._offset(lockstep, index, obs)
        return math.dist(offset, origin)

    def in_air_refusal(self, lockstep: Any, limits: InAirLimits = IN_AIR_LIMITS) -> str:
        """Held: why PX4 cannot fly on into the next episode ('' when every vehicle can; see
        `in_air`), from fresh reports (`_observe_fresh`)."""
        self._observe_fresh(lockstep)
        for index, autopilot in enumerate(self.autopilots):
            obs = autopilot.poll()
            state = lockstep.sim.state(index)
            velocity_error = (math.dist(obs.velocity_ned_m_s, state.velocity_ned_m_s)
                              if obs.velocity_ned_m_s is not None else math.inf)
            reason = in_air_refusal(obs, state, self.estimate_error_m(lockstep, index), velocity_error, limits)
            if reason:
                detail = describe(obs, state, self._estimated_height_m(lockstep, index, obs), time.monotonic())
                log.info("PX4 instance %d refuses to fly on: %s (%s)", autopilot.instance, reason, detail)
                return f"vehicle {index} (PX4 instance {autopilot.instance}): {reason} ({detail})"
        return ""

    def _estimated_height_m(self, lockstep: Any, index: int, obs: Px4Observation) -> float | None:
        """PX4's estimate of the height in the truth's frame (its local z moved by the origin
        offset found when it became ready), or None before it reported one."""
        origin = self._origin_offsets[index]
        if obs.position_ned_m is None or origin is None:
            return None
        shift = lockstep.sensors[index].position_offset_ned_m
        return -(obs.position_ned_m[2] + origin[2] - float(shift[2]))

    def _observe_fresh(self, lockstep: Any) -> None:
        """Held: poll every PX4's reports; where they were last made fresh more than
        `IN_AIR_FRESH_S` of simulated time ago, first run `IN_AIR_OBSERVE_S` (the observer's
        socket may have overflowed while nobody read it, keeping old reports and dropping new
        ones)."""
        for autopilot in self.autopilots:
            autopilot.poll()
        if lockstep.stats.steps - self._polled_at_step > lockstep.steps_for_rounded(IN_AIR_FRESH_S):
            lockstep.run_for(IN_AIR_OBSERVE_S)
        self.check_alive()
        self._polled_at_step = lockstep.stats.steps

    def estimates(self, lockstep: Any) -> list[Estimate]:
        """Held: what each PX4 estimates of its vehicle, from fresh reports (as
        `in_air_refusal`)."""
        self._observe_fresh(lockstep)
        estimates = []
        for index, autopilot in enumerate(self.autopilots):
            obs, origin = autopilot.poll(), self._origin_offsets[index]
            if obs.velocity_ned_m_s is None or obs.attitude_rad is None or origin is None:
                raise Px4Error(f"PX4 instance {autopilot.instance}: no estimate reported yet")
            error = tuple(o - g for o, g in zip(self._offset(lockstep, index, obs), origin, strict=True))
            estimates.append(Estimate(position_error_ned_m=error,  # type: ignore[arg-type]
                                      velocity_ned_m_s=tuple(obs.velocity_ned_m_s),  # type: ignore[arg-type]
                                      roll_pitch_rad=obs.attitude_rad[:2], yaw_rad=obs.attitude_rad[2]))
        return estimates

    def reset_in_place(self, lockstep: Any, reset: Callable[[], None] | None = None, *,
                       tolerance_m: float = 0.3,
                       timeout_s: float = 120.0, max_sim_s: float = 120.0) -> float:
        """The alternative to `restart`: keep PX4 running, force-disarm it, `reset()` the
        simulation (default `lockstep.reset_simulation()`: the vehicle jumps back to its spawn) and run until PX4's estimate has
        followed (within `tolerance_m`, nearly at rest) and its pre-arm checks pass again.
        Returns the wall seconds. PX4's clock keeps running forward (the link makes wire time
        monotonic across the reset)."""
        start = time.monotonic()
        deadline = start + timeout_s
        disarm = mavlink.dialect.MAV_CMD_COMPONENT_ARM_DISARM
        for autopilot in self.autopilots:
            autopilot.command(disarm, 0, 21196)  # 21196: force, even in the air

        def disarmed() -> bool:
            self.check_alive()
            return all(not a.poll().armed for a in self.autopilots)

        if not lockstep.run_until(disarmed, max_seconds=10.0, check_every_s=0.02):
            raise Px4Error("PX4 did not disarm for the in-place reset")
        (reset or lockstep.reset_simulation)()
        for autopilot in self.autopilots:
            autopilot.observation.prearm_ok = False
            autopilot.observation.position_ned_m = None

        waiting_for = [""]  # the last check that held the reset up, for the error (why it did not converge)

        def converged() -> bool:
            self.check_alive()
            if time.monotonic() > deadline:
                raise Px4Error(f"PX4 estimate did not follow the in-place reset within {timeout_s} s "
                               f"({waiting_for[0]})")
            for index, autopilot in enumerate(self.autopilots):
                obs = autopilot.poll()
                if not obs.prearm_ok or obs.velocity_ned_m_s is None:
                    waiting_for[0] = (f"vehicle {index}: pre-arm checks {'pass' if obs.prearm_ok else 'fail'}, "
                                      f"velocity {'reported' if obs.velocity_ned_m_s else 'not reported'}")
                    return False
                error_m = self.estimate_error_m(lockstep, index)
                if error_m > tolerance_m:
                    waiting_for[0] = f"vehicle {index}: estimate {error_m:.2f} m from the truth"
                    return False
                speed = math.hypot(*obs.velocity_ned_m_s)
                if speed > 0.2:
                    waiting_for[0] = f"vehicle {index}: estimated speed {speed:.2f} m/s"
                    return False
            return True

        if not lockstep.run_until(converged, max_seconds=max_sim_s, check_every_s=0.1):
            raise Px4Error(f"PX4 estimate did not follow the in-place reset in {max_sim_s} s simulated "
                           f"({waiting_for[0]})")
        return time.monotonic() - start

    def restart(self, lockstep: Any, reset: Callable[[], None] | None = None, *,
                connect_timeout_s: float = 30.0, ready_timeout_s: float = 120.0) -> float:
        """Episode restart: hold, stop every PX4, drop the links, `reset()` the simulation
        (default: `lockstep.reset_simulation()`, physics and sensors), start PX4 again,
        reconnect and wait until ready. Returns restart-to-ready wall seconds."""
        start = time.monotonic()
        lockstep.hold()
        self.stop()
        for link in lockstep.links:
            link.disconnect()
        (reset or lockstep.reset_simulation)()
        self.start()
        self.connect(lockstep.links, connect_timeout_s)
        self.wait_ready(lockstep, timeout_s=ready_timeout_s)
        return time.monotonic() - start

    def __enter__(self) -> Px4Fleet:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


class Px4SitlFleet(AutopilotFleet):
    """`px4`: a session's real PX4 SITL processes (a `Px4Fleet`), started, connected and run
    until observed ready; a reset restarts them (PX4's estimator cannot follow a teleport
    reliably), so MAVSDK clients should reconnect. Mode and armed flag come from PX4's own
    HEARTBEAT on its GCS link (`Px4Autopilot.poll`), read when asked."""

    resets_in_place = False
    resets_in_air = True
    last_instance = PX4_LAST_OWN_API_INSTANCE  # above 9 PX4 gives no API port of its own (ports.py)

    def __init__(self, config: FleetConfig) -> None:
        super().__init__(config)
        shared = [i for i in self.instances if i > PX4_LAST_OWN_API_INSTANCE]
        if len(shared) > 1:
            raise ConfigError(
                f"instance_base: PX4 instances above {PX4_LAST_OWN_API_INSTANCE} all send their "
                f"MAVLink API to UDP {PX4_SHARED_API_PORT}; with several vehicles use instances "
                f"0..{PX4_LAST_OWN_API_INSTANCE}, got {self.instances[0]}..{self.instances[-1]}")
        self.px4: Px4Fleet | None = None
        self._temp_run_dir: Path | None = None

    def start(self, links: Sequence[Any]) -> list[Any]:
        config = self.config
        # (the session holds the instances' claim: `autopilot.allocation`)
        run_dir = config.run_dir
        if run_dir is None:
            # Ours, so removed on close; pass run_dir to keep PX4's console logs.
            run_dir = self._temp_run_dir = make_temp_run_dir()
        # px4 resolves px4_params/ itself (wall timeouts via env + read-back); only extras here.
        px4_config = Px4Config.create(config.px4_bin, run_dir, rootfs=config.px4_rootfs,
                                      speed_factor=config.speed_factor, home=config.world.home,
                                      extra_params=config.params, keep_logs=self._temp_run_dir is None,
                                      api_streams="client" if config.api_telemetry == "client" else "onboard")
        self.px4 = Px4Fleet(px4_config, self.instances)
        self.px4.start()
        return []

    @property
    def reads_hil_ground_truth(self) -> bool:
        # PX4 asks for HIL_STATE_QUATERNION at 200 Hz but only publishes *_groundtruth topics
        # from it, which nothing but its logger reads (not the estimator, not the controllers).
        mode = load_param_overrides(extra=self.config.params).get("SDLOG_MODE")
        return mode is None or mode.value != -1

    def _fleet(self) -> Px4Fleet:
        if self.px4 is None:
            raise Px4Error("PX4 fleet not started")
        return self.px4

    def wait_ready(self, lockstep: Any) -> None:
        self._fleet().wait_ready(lockstep)

    def check(self) -> list[AutopilotFault]:
        faults = []
        for vehicle, autopilot in enumerate(self.px4.autopilots if self.px4 is not None else ()):
            try:
                autopilot.check_alive()
            except Px4Error as exc:
                faults.append(AutopilotFault(str(exc), vehicle=vehicle, instance=autopilot.instance,
                                             reason="dead"))
        return faults

    def explain(self, error: BaseException) -> BaseException:
        explained = self.px4.explain(error) if self.px4 is not None else error
        if isinstance(explained, Px4Died):
            return AutopilotFault(str(explained), vehicle=self.instances.index(explained.instance),
                                  instance=explained.instance, reason="dead")
        return super().explain(explained)

    def close(self) -> None:
        if self.px4 is not None:
            self.px4.stop()
        if self._temp_run_dir is not None:
            shutil.rmtree(self._temp_run_dir, ignore_errors=True)
            self._temp_run_dir = None

    def restart(self, lockstep: Any, reset_simulation: Callable[[], None] | None = None) -> None:
        try:
            self._fleet().restart(lockstep, reset_simulation or (lambda: None),
                                  connect_timeout_s=self.config.connect_timeout_s or 30.0)
        except HilError as exc:
            raise self.explain(exc) from exc

    def in_air_refusal(self, lockstep: Any) -> str:
        try:
            return self._fleet().in_air_refusal(lockstep)
        except HilError as exc:
            raise self.explain(exc) from exc
        except Px4Error as exc:  # died: the caller restarts it
            return str(exc).splitlines()[0]

    def estimates(self, lockstep: Any) -> list[Estimate]:
        try:
            return self._fleet().estimates(lockstep)
        except Px4Error as exc:  # no report yet: the caller restarts instead
            raise SessionError(str(exc)) from exc

    def deliver_setpoints(self, velocities_ned_m_s: Mapping[int, Sequence[float]],
                          serve_until: ServeUntil, timeout_s: float) -> None:
        # PX4 reads its MAVLink socket in wall time even while lockstep holds its clock: wait
        # until MAVSDK sent the setpoints and each PX4 read and handled them (delivery.py).
        receivers = [(autopilot.pid, api_bind_port(autopilot.instance))
                     for autopilot in self._fleet().autopilots
                     if autopilot.instance in velocities_ned_m_s and autopilot.pid is not None]
        try:
            observed = wait_delivered(receivers, timeout_s)
        except TimeoutError as exc:
            raise SessionError(f"velocity setpoints not delivered to PX4: {exc}") from exc
        if not observed:  # not observable here (not Linux, no registered MAVSDK thread): a fixed wait
            time.sleep(PX4_SETPOINT_DELIVERY_S)  # a delivery wait, not a flight timing

    def summary(self, vehicle: int, link: Any) -> VehicleSummary:
        # poll(): the observation only moves when read (it was read once at readiness, so the
        # status line said "Hold disarmed" for a whole flight).
        observation = self._fleet().autopilots[vehicle].poll()
        if not observation.heartbeat:
            return link_summary(link)
        return observation.summary()

    def ports(self, vehicle: int) -> VehiclePorts:
        return vehicle_ports(self.instances[vehicle], px4=True)
