"""`Lockstep`: one simulated clock for every vehicle, driven by their autopilots' answers.

Each step at simulated time t:
  1. every vehicle's sensors are sampled at t and sent on its `HilLink` (one HIL_SENSOR id 0,
     plus GPS / ground truth when due);
  2. the `pumps` run: callables through which in-process autopilots (the stub's HIL client)
     read their own sockets and answer in this same thread, with no context switch;
  3. once a vehicle's autopilot has started answering (its first HIL_ACTUATOR_CONTROLS), the
     step waits for the answer to t from every such vehicle (select on the link sockets,
     pumps run again between short waits); an answer that does not come within
     `actuator_timeout_s` (wall) is a `LockstepTimeout`, raised or counted and logged;
  4. physics advances one step with the latest motor commands, then the `after_step`
     observers run (e.g. a collision log).

Before a vehicle's autopilot answers (PX4 booting), steps do not wait for it: PX4 blocks its
boot until the first HIL_SENSOR and only answers once its control chain runs.

Speed factor F paces simulated time at F x wall time (any F > 0); F = 0 runs as fast as the
autopilots answer. This module is the only place that reads the wall clock. Holding is simply
not stepping: PX4 in lockstep is frozen without sensor messages; `idle()` services the pumps
while held so an in-process autopilot still answers its MAVLink API.
"""

from __future__ import annotations

import logging
import select
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from sitl_bridge.hil.errors import LockstepTimeout
from sitl_bridge.hil.link import HilLink
from sitl_bridge.sensors.suite import offset_within_bounds
from sitl_bridge.world.clock import whole_steps

log = logging.getLogger(__name__)

Pump = Callable[[], Any]

# While waiting with in-process pumps, wake this often to run them again.
PUMP_INTERVAL_S = 0.0005
# Pacing: when simulated time falls this far behind the target (a stall, a debugger), restart
# the pacing reference instead of running flat out to catch up.
MAX_LAG_S = 0.5
# With F = 0, steps before the autopilots answer are paced at this factor: PX4 boots in wall
# time and streaming sensors any faster only burns CPU.
PRESTREAM_SPEED_FACTOR = 10.0


def parse_speed_factor(text: str | float) -> float:
    """`--speed-factor` value: a number >= 0, or 'max' (= 0, as fast as lockstep allows)."""
    if isinstance(text, str) and text.strip().lower() in ("max", "inf", "0"):
        return 0.0
    value = float(text)
    if not value >= 0.0 or value == float("inf"):
        raise ValueError(f"speed factor must be a number >= 0 or 'max', got {text!r}")
    return value


@dataclass
class LockstepStats:
    """Counters since construction. `wall_s`/`sim_s` cover running time only (not holds)."""

    steps: int = 0
    timeouts: int = 0
    wait_s: float = 0.0  # wall time spent waiting for autopilot answers
    sim_s: float = 0.0
    wall_s: float = 0.0

    @property
    def real_time_factor(self) -> float:
        """Simulated seconds per wall second over all running segments."""
        return self.sim_s / self.wall_s if self.wall_s > 0 else 0.0


class Lockstep:
    """The lockstep loop over one `Simulation`, its per-vehicle sensor suites and HIL links.

    Args:
        sim: the physics (`time_us`, `step_us`, `state(i)`, `vehicle_vector(i)`, `step(commands)`).
        sensors: one `SensorSuite` per vehicle (`sample_values`, `ground_truth`).
        links: one connected `HilLink` per vehicle (vehicle i <-> links[i]).
        speed_factor: F x real time; 0 = as fast as possible.
        pumps: callables run after the sensor messages are sent (see module docstring).
        actuator_timeout_s: wall time to wait for an answer before it is a timeout.
        on_timeout: "raise" (LockstepTimeout) or "continue" (log, count, reuse the last
            commands; a late answer is then matched to a later step).
    """

    def __init__(
        self,
        sim: Any,
        sensors: Sequence[Any],
        links: Sequence[HilLink],
        *,
        speed_factor: float = 1.0,
        pumps: Iterable[Pump] = (),
        actuator_timeout_s: float = 5.0,
        on_timeout: str = "raise",
    ) -> None:
        if len(sensors) != len(links):
            raise ValueError(f"{len(sensors)} sensor suites for {len(links)} links")
        if on_timeout not in ("raise", "continue"):
            raise ValueError(f"on_timeout must be 'raise' or 'continue', got {on_timeout!r}")
        self.sim = sim
        self.sensors = list(sensors)
        self.links = list(links)
        self.pumps: list[Pump] = list(pumps)
        # run after every physics step, in the stepping thread: e.g. to collect the step's
        # `sim.collisions()` (SimSession's collision log); not while held
        self.after_step: list[Callable[[], Any]] = []
        self.actuator_timeout_s = actuator_timeout_s
        self.on_timeout = on_timeout
        self.stats = LockstepStats()
        self._speed_factor = parse_speed_factor(speed_factor)
        self._running = False
        self._pace_factor = 0.0
        self._anchor_wall = 0.0
        self._anchor_sim_us = 0
        self._segment_wall0 = 0.0
        self._segment_sim0_us = 0
        self._segment_end_wall = 0.0
        self._last_rtf = 0.0

    # -- configuration ----------------------------------------------------------------------
    @property
    def speed_factor(self) -> float:
        """Target simulated seconds per wall second (0: as fast as possible)."""
        return self._speed_factor

    @speed_factor.setter
    def speed_factor(self, value: float | str) -> None:
        self._speed_factor = parse_speed_factor(value)
        if self._running:
            self._reanchor()

    @property
    def time_us(self) -> int:
        """Simulated time (the simulation's clock)."""
        return self.sim.time_us

    @property
    def held(self) -> bool:
        """True between runs: nothing advances until the next step."""
        return not self._running

    def accept_all(self, timeout_s: float) -> bool:
        """Wait (wall, shared budget) until every link has an autopilot connected."""
        deadline = time.monotonic() + timeout_s
        return all(link.accept(max(0.0, deadline - time.monotonic())) for link in self.links)

    # -- stepping ---------------------------------------------------------------------------
    def step(self) -> None:
        """One lockstep step for all vehicles (see module docstring), paced by the speed
        factor. Calling it after a hold starts a new running segment."""
        if not self._running:
            self._start_segment()
        sim = self.sim
        time_us = sim.time_us
        links = self.links
        for index, suite in enumerate(self.sensors):
            # plain values, no SensorFrame; the ground truth (a VehicleState) only when sent
            link = links[index]
            truth = suite.ground_truth(sim.state(index)) if link.state_due(time_us) else None
            link.send_sensor_values(time_us, suite.sample_values(sim.vehicle_vector(index), time_us), truth)
        for pump in self.pumps:
            pump()
        self._collect_answers(time_us)
        sim.step([link.command for link in links])
        for observer in self.after_step:
            observer()
        self.stats.steps += 1
        self._pace()

    def run_steps(self, steps: int, until: Callable[[], bool] | None = None) -> int:
        """Run `steps` steps (stopping early when `until()` turns true after a step), then
        hold. Returns the number of steps run."""
        done = 0
        try:
            while done < steps:
                self.step()
                done += 1
                if until is not None and until():
                    break
        finally:
            self.hold()
        return done

    def run_for(self, seconds: float, until: Callable[[], bool] | None = None) -> int:
        """Run exactly `seconds` of simulated time (a whole number of steps), then hold:
        every vehicle and autopilot frozen until the next call. Returns steps run."""
        return self.run_steps(self.steps_for(seconds), until)

    def run_until(self, predicate: Callable[[], bool], max_seconds: float,
                  check_every_s: float = 0.1) -> bool:
        """Step until `predicate()` is true (checked every `check_every_s` of simulated time)
        or `max_seconds` of simulated time passed; then hold. Returns the predicate's value."""
        chunk = max(1, self.steps_for_rounded(check_every_s))
        remaining = self.steps_for_rounded(max_seconds)
        try:
            while not predicate():
                if remaining <= 0:
                    return False
                count = min(chunk, remaining)
                for _ in range(count):
                    self.step()
                remaining -= count
            return True
        finally:
            self.hold()

    def steps_for(self, seconds: float) -> int:
        """The number of steps in `seconds`; ValueError unless it is a whole number."""
        return whole_steps(seconds, self.sim.step_us)

    def steps_for_rounded(self, seconds: float) -> int:
        """The number of whole steps nearest to `seconds`."""
        return whole_steps(seconds, self.sim.step_us, exact=False)

    def hold(self) -> None:
        """End the running segment: nothing moves until the next step. (PX4 is frozen in
        lockstep; in-process autopilots keep answering their API through `idle()`.) The pumps
        run once more, held: what in-process autopilots queued while running (batched
        telemetry) goes out before anyone reads it."""
        if self._running:
            self._running = False
            for pump in self.pumps:
                try:
                    pump()
                except Exception as exc:  # noqa: BLE001 - a hold must not fail (maybe in a finally)
                    log.debug("pump failed while holding: %s (the next step or idle reports it)", exc)
            now = time.monotonic()
            self._segment_end_wall = now
            self.stats.sim_s += (self.sim.time_us - self._segment_sim0_us) / 1e6
            self.stats.wall_s += now - self._segment_wall0
            self._last_rtf = self._segment_rtf(now)

    def reset_simulation(self, seed: int | None = None,
                         sensor_seeds: Sequence[int | None] | None = None, *,
                         place: Callable[[Any], None] | None = None, continuous: bool = False,
                         shifts_ned_m: Sequence[Sequence[float]] | None = None) -> bool:
        """Hold, reset the simulation in place (time 0, vehicles re-spawned) and every sensor
        suite with it (their sample schedules follow simulated time). The links keep the
        autopilots' clock monotonic across the jump. Sensor suite i is re-seeded with
        `sensor_seeds[i]` when given, else `seed + i` (None: not re-seeded).

        `place(sim)` runs after the re-spawn (e.g. teleports the vehicles into the air).
        `continuous`: every suite's measured position offset is set so that the position it
        reports does not jump (new offset = old offset + old position - new position): an
        autopilot flying on these sensors sees no teleport; `shifts_ned_m` (per suite) then moves
        each reported position by that much on top (the in-air reset: onto the autopilot's own
        estimate). Returns False (offsets left at zero,
        the simulation reset all the same) when an offset would exceed the suites' bound
        (`sensors.suite.MAX_POSITION_OFFSET_M`); True otherwise."""
        self.hold()
        # what each suite reports now: the true position plus its offset
        measured = [tuple(float(p) + o for p, o in zip(self.sim.state(i).position_ned_m,
                                                        suite.position_offset_ned_m, strict=True))
                    for i, suite in enumerate(self.sensors)] if continuous else []
        self.sim.reset(seed)
        if place is not None:
            place(self.sim)
        for index, suite in enumerate(self.sensors):
            if sensor_seeds is not None:
                suite.reset(sensor_seeds[index])
                continue
            suite.reset(None if seed is None else seed + index)
        if not continuous:
            return True
        offsets = []
        shifts = shifts_ned_m or [(0.0, 0.0, 0.0)] * len(measured)
        for index, (seen, shift) in enumerate(zip(measured, shifts, strict=True)):
            position = self.sim.state(index).position_ned_m
            offsets.append(tuple(s + float(d) - float(p) for s, d, p in zip(seen, shift, position, strict=True)))
        if not all(offset_within_bounds(offset) for offset in offsets):
            return False
        for suite, offset in zip(self.sensors, offsets, strict=True):
            suite.position_offset_ned_m = offset
        return True

    def idle(self, timeout_s: float = 0.0, until: Callable[[], bool] | None = None) -> bool:
        """Without advancing time: run the pumps and read the links once, then keep doing so
        until `timeout_s` (wall) has passed, or, with `until`, as soon as `until()` holds after
        a pass (checked every `PUMP_INTERVAL_S`: what it waits for may come on a socket the
        links do not see, e.g. an in-process stub's MAVLink API). Returns `until()` (True
        without one)."""
        deadline = time.monotonic() + timeout_s
        slice_s = PUMP_INTERVAL_S if until is not None else PUMP_INTERVAL_S * 20
        while True:
            for pump in self.pumps:
                pump()
            for link in self.links:
                link.poll()
            if until is not None and until():
                return True
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return until is None
            self._wait_readable(self.links, min(remaining, slice_s) if self.pumps else remaining)

    # -- real-time factor ---------------------------------------------------------------------
    @property
    def real_time_factor(self) -> float:
        """Achieved simulated/wall time of the current running segment, or of the last one
        while held (0 before any)."""
        if self._running:
            return self._segment_rtf(time.monotonic())
        return self._last_rtf

    def _segment_rtf(self, now: float) -> float:
        wall = now - self._segment_wall0
        sim_s = (self.sim.time_us - self._segment_sim0_us) / 1e6
        return sim_s / wall if wall > 0 else 0.0

    # -- internals ----------------------------------------------------------------------------
    def _start_segment(self) -> None:
        self._running = True
        self._segment_wall0 = time.monotonic()
        self._segment_sim0_us = self.sim.time_us
        self._reanchor()

    def _reanchor(self) -> None:
        self._anchor_wall = time.monotonic()
        self._anchor_sim_us = self.sim.time_us

    def _collect_answers(self, time_us: int) -> None:
        links = self.links
        pumps = self.pumps
        for link in links:
            # An autopilot in another process (PX4) has not answered a sensor message sent
            # microseconds ago: skip that read (a syscall that finds nothing, every step) and
            # let select below wait for it. Still read a link whose first answer is awaited
            # (answered() is true until then) and, with pumps, in-process answers.
            if pumps or not link.actuators_flowing:
                link.poll()
        pending = [link for link in links if not link.answered()]
        if not pending:
            return
        start = time.monotonic()
        deadline = start + self.actuator_timeout_s
        while pending:
            now = time.monotonic()
            remaining = deadline - now
            if remaining <= 0:
                self.stats.wait_s += now - start
                self._timeout(pending, time_us)
                return
            self._wait_readable(pending, min(remaining, PUMP_INTERVAL_S) if pumps else remaining)
            for link in pending:
                link.poll()
            for pump in pumps:
                pump()
            if pumps:
                for link in pending:
                    link.poll()
            pending = [link for link in pending if not link.answered()]
        self.stats.wait_s += time.monotonic() - start

    @staticmethod
    def _wait_readable(links: Sequence[HilLink], timeout_s: float) -> None:
        fds = [fd for fd in (link.fileno() for link in links) if fd >= 0]
        if fds:
            select.select(fds, [], [], timeout_s)
        elif timeout_s > 0:
            time.sleep(timeout_s)

    def _timeout(self, pending: list[HilLink], time_us: int) -> None:
        self.stats.timeouts += 1
        instances = tuple(link.instance for link in pending)
        for link in pending:
            link.stats.timeouts += 1
        message = (
            f"lockstep: vehicle(s) {', '.join(map(str, instances))} did not answer the step at "
            f"t={time_us / 1e6:.3f} s with HIL_ACTUATOR_CONTROLS within {self.actuator_timeout_s} s"
        )
        if self.on_timeout == "raise":
            raise LockstepTimeout(message, instances=instances, time_us=time_us)
        log.warning("%s; continuing with the last commands (%d timeouts)", message, self.stats.timeouts)

    def _pace(self) -> None:
        factor = self._speed_factor
        if factor <= 0.0:
            for link in self.links:  # a plain loop: all(generator) costs more, every step
                if not link.actuators_flowing:
                    factor = PRESTREAM_SPEED_FACTOR
                    break
        if factor != self._pace_factor:
            self._pace_factor = factor
            self._reanchor()
        if factor <= 0.0:
            return
        target = self._anchor_wall + (self.sim.time_us - self._anchor_sim_us) / 1e6 / factor
        now = time.monotonic()
        if now >= target:
            if now - target > MAX_LAG_S:
                self._reanchor()
            return
        # Ahead of schedule: wait, but keep in-process autopilots and the links serviced.
        while True:
            remaining = target - now
            if remaining <= 0:
                return
            if self.pumps:
                for pump in self.pumps:
                    pump()
                self._wait_readable(self.links, min(remaining, PUMP_INTERVAL_S * 4))
            else:
                self._wait_readable(self.links, remaining)
            for link in self.links:
                link.poll()
            now = time.monotonic()
