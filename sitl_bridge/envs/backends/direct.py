"""`direct` backend: physics, sensors and the stub autopilot in one tight loop, no sockets.

The fast path for training. Each physics step runs in the lockstep order of the protocol path
(`sitl_bridge.hil.lockstep`): sample every vehicle's sensors at t, let its `StubAutopilot` answer
with motor commands, step the physics. Commands reach the autopilot through the same commander
methods the stub's MAVLink API calls (arm, takeoff, mode switch, offboard velocity setpoint),
in the same order as the `stub` backend sends them through MAVSDK, so both fly alike. The
offboard setpoint is refreshed at MAVSDK's 20 Hz (in simulated time) so the offboard-loss
failsafe never fires. The lidar is cast once per `fly`/`reset` (observations need it only then).

Estimator (`estimator=`, see `base.ESTIMATORS`): `sensors` (default) samples every vehicle's
`SensorSuite` each step for the stub's sensor-fusion estimator; `ground_truth` builds only the
ground-truth frame (`SensorSuite.truth_frame`: no sensor simulation, no noise) for the stub's
`GroundTruthEstimator`, the same estimator the `stub` backend then runs on HIL_STATE_QUATERNION.

Fused loop: per vehicle and step, compiled calls composed from the components' own kernels,
with no frame or command objects. In a steady step (the commander's `steady`: OFFBOARD, takeoff
or hold, or disarmed, with nothing to decide; see `commander.steady_output`) with no GPS sample
due, one call, `vehicle_step`: the suite's IMU/mag `sense`, the estimator's
`estimator_imu_step` and `baro_update`, the commander's `steady_output` test, the stub's
`steady_step` (position loop when due, `inner_loop`; motors off when disarmed) and the
simulation's `vehicle_wrench`; the Python left is the bookkeeping (`StubAutopilot.flew_steady`),
and the estimate object is brought up to date (`SensorEstimator.refresh`) only when Python may
read it (before `until`, at the end). When
the commander has something to decide, `vehicle_step` stops after the estimator and the step
goes on as below. With `ground_truth`, `truth_estimate` and `GroundTruthEstimator.finish`
every step (the estimate stays current), then in a steady step `truth_vehicle_step` (the same
tail, `steady_wrench`, on the truth). Otherwise two calls: `sense_and_estimate` (`sense`, then
`estimator_imu_step`; with `ground_truth`, `truth_estimate`: the suite's `truth_of_vector`,
then the ground-truth estimator's `relative_estimate`) and, after the Python commander and
position loop (`StubAutopilot.prepare`), `control_and_rotors` (`inner_loop`, then
`vehicle_wrench`). Baro and GPS sampling (`SensorSuite.slow_samples`, 50 / 5 Hz) and the GPS
estimator update (`SensorEstimator.finish`) stay Python. The result is the same computation
as `StubAutopilot.update(SensorSuite.sample(...))` (or `truth_frame`) + `Simulation.step`, in
the same order, bit for bit.

Reset: in place, the same steps as `SimSession.reset` for in-process stubs: the simulation
re-spawned from the episode's seed (time 0), sensor noise re-seeded (`sensor_seed`), every
autopilot rebooted with `StubAutopilot.reset` (the short warm alignment; the autopilots are
built once, with the backend). Then, unless `takeoff`, every vehicle is placed hovering at the start
altitude with its autopilot settled there (`autopilot.stub.in_air_start`), and only offboard
and the settle are flown.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from sitl_bridge.autopilot.modes import HOLD, MainMode, custom_mode
from sitl_bridge.autopilot.stub import commander as stub_commander
from sitl_bridge.autopilot.stub.autopilot import (
    StubAutopilot,
    inner_loop,
    inner_loop_kernel,
    steady_step,
)
from sitl_bridge.autopilot.stub.commander import NOT_STEADY, STEADY_OFF, steady_output
from sitl_bridge.autopilot.stub.estimator import (
    ESTIMATOR_STATE,
    GROUND_TRUTH_STATE,
    attitude_and_rates,
    baro_update,
    current_values,
    estimate_values,
    estimator_imu_step,
    position_valid,
    relative_estimate,
)
from sitl_bridge.autopilot.stub.in_air_start import place_hovering
from sitl_bridge.autopilot.stub.modes import CommandResult, LandedState
from sitl_bridge.autopilot.stub.params import ParamTable
from sitl_bridge.envs.backends.base import EPISODE_START, BackendError, CollisionFlags, Snapshot
from sitl_bridge.envs.options import EnvOptions
from sitl_bridge.jit import dual, kernel
from sitl_bridge.physics import MotorCommand, Simulation
from sitl_bridge.physics.simulation import vehicle_wrench
from sitl_bridge.sensors import SensorSuite, environment, sensor_seed
from sitl_bridge.sensors.lidar import Lidar
from sitl_bridge.sensors.suite import sense, truth_of_vector
from sitl_bridge.world import World
from sitl_bridge.world.clock import whole_steps

SETPOINT_PERIOD_S = 0.05
"""MAVSDK re-sends offboard setpoints at 20 Hz; the direct backend refreshes them as often."""


_HOLD_MODE = custom_mode(*HOLD)
_NAN = float("nan")


@kernel(sense, estimator_imu_step)
def sense_and_estimate(x: np.ndarray, imu_noise: np.ndarray, imu_row: int, mag_noise: np.ndarray, mag_row: int,
                       sense_constants: np.ndarray, est_state: np.ndarray, est_gains: np.ndarray, dt: float,
                       time_us: int) -> tuple:
    """`SensorSuite.sample`'s IMU/mag part, then `SensorEstimator.update`'s per-step part."""
    a0, a1, a2, g0, g1, g2, m0, m1, m2 = sense(x, imu_noise, imu_row, mag_noise, mag_row, sense_constants)
    return estimator_imu_step(est_state, est_gains, a0, a1, a2, g0, g1, g2, mag_row >= 0, m0, m1, m2, dt, time_us)


@kernel(sense, estimator_imu_step, environment, inner_loop_kernel, stub_commander, vehicle_wrench)
def vehicle_step(x: np.ndarray, imu_noise: np.ndarray, imu_row: int, mag_noise: np.ndarray, mag_row: int,
                 sense_constants: np.ndarray, est_state: np.ndarray, est_gains: np.ndarray, dt: float, time_us: int,
                 baro_hpa: float, plan: np.ndarray, last_us: int, last_run_us: int, ctl: np.ndarray,
                 pc_state: np.ndarray, pc_gains: np.ndarray, att_gains: np.ndarray, rate_state: np.ndarray,
                 rate_gains: np.ndarray, mix_constants: np.ndarray, mix_state: np.ndarray, rotor_constants: np.ndarray,
                 rotor_speeds: np.ndarray) -> tuple:
    """A steady commander's whole step (module docstring): `sense_and_estimate` and the baro
    sample (`baro_hpa`, NaN: none) folded in as `SensorEstimator.finish` does, then, when
    `steady_output` finds a steady step, `steady_step` (or motors off) and the rotors' world
    wrench. Returns (status, force, torque): status 0 when the commander must decide (only the
    estimator ran), 1 flown, 2 flown with the position loop, 3 disarmed."""
    a0, a1, a2, g0, g1, g2, m0, m1, m2 = sense(x, imu_noise, imu_row, mag_noise, mag_row, sense_constants)
    estimator_imu_step(est_state, est_gains, a0, a1, a2, g0, g1, g2, mag_row >= 0, m0, m1, m2, dt, time_us)
    if baro_hpa == baro_hpa:
        baro_update(est_state, baro_hpa, time_us, dt)
    q, rates, pos, vel, acc, _, _, _, _ = estimate_values(est_state, time_us)
    return steady_wrench(plan, time_us, q, rates, pos, vel, acc, position_valid(est_state, time_us), last_us,
                         last_run_us, ctl, pc_state, pc_gains, att_gains, rate_state, rate_gains, mix_constants,
                         mix_state, x, rotor_constants, rotor_speeds)


@kernel(sense, estimator_imu_step, inner_loop_kernel, stub_commander, vehicle_wrench)
def truth_vehicle_step(x: np.ndarray, origin: np.ndarray, time_us: int, plan: np.ndarray, last_us: int,
                       last_run_us: int, ctl: np.ndarray, pc_state: np.ndarray, pc_gains: np.ndarray,
                       att_gains: np.ndarray, rate_state: np.ndarray, rate_gains: np.ndarray,
                       mix_constants: np.ndarray, mix_state: np.ndarray, rotor_constants: np.ndarray,
                       rotor_speeds: np.ndarray) -> tuple:
    """`vehicle_step` with the ground-truth estimate (`truth_estimate`'s, the position valid),
    after `GroundTruthEstimator.finish` has taken the same estimate: (status, force, torque)."""
    q, rates, vel, acc, pos = truth_of_vector(x)
    q, rates, pos, vel, acc, _, _, _ = relative_estimate(origin, q, rates, vel, acc, pos[0], pos[1], pos[2])
    return steady_wrench(plan, time_us, q, rates, pos, vel, acc, True, last_us, last_run_us, ctl, pc_state,
                         pc_gains, att_gains, rate_state, rate_gains, mix_constants, mix_state, x, rotor_constants,
                         rotor_speeds)


@dual
def steady_wrench(plan: np.ndarray, time_us: int, q: tuple, rates: tuple, pos: tuple, vel: tuple, acc: tuple,
                  pos_valid: bool, last_us: int, last_run_us: int, ctl: np.ndarray, pc_state: np.ndarray,
                  pc_gains: np.ndarray, att_gains: np.ndarray, rate_state: np.ndarray, rate_gains: np.ndarray,
                  mix_constants: np.ndarray, mix_state: np.ndarray, x: np.ndarray, rotor_constants: np.ndarray,
                  rotor_speeds: np.ndarray) -> tuple:
    """The commander's `steady_output` on this step's estimate, then `steady_step` (or motors
    off) and the rotors' world wrench: (status, force, torque), status as `vehicle_step`'s."""
    output = steady_output(plan, time_us, pos[2], vel[0], vel[1], vel[2], pos_valid)
    if output == NOT_STEADY:
        return 0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)
    if output == STEADY_OFF:
        force, torque = vehicle_wrench(x, rotor_constants, rotor_speeds, 0.0, 0.0, 0.0, 0.0, False)
        return 3, force, torque
    outer_ran, u0, u1, u2, u3 = steady_step(plan, ctl, pc_state, pc_gains, att_gains, rate_state, rate_gains,
                                            mix_constants, mix_state, q, rates, pos, vel, acc, time_us, last_us,
                                            last_run_us)
    force, torque = vehicle_wrench(x, rotor_constants, rotor_speeds, u0, u1, u2, u3, True)
    return 2 if outer_ran else 1, force, torque


@kernel(sense, estimator_imu_step)
def truth_estimate(x: np.ndarray, origin: np.ndarray) -> tuple:
    """`SensorSuite.truth_frame`'s truth, then `GroundTruthEstimator.update` (origin known)."""
    q, rates, vel, acc, pos = truth_of_vector(x)
    return relative_estimate(origin, q, rates, vel, acc, pos[0], pos[1], pos[2])


@kernel(inner_loop_kernel, estimator_imu_step, sense, vehicle_wrench)
def control_and_rotors(ctl: np.ndarray, att_gains: np.ndarray, rate_state: np.ndarray, rate_gains: np.ndarray,
                       mix_constants: np.ndarray, mix_state: np.ndarray, est_state: np.ndarray, truth: bool,
                       yaw_rate_ff: float, dt_s: float, landed: bool, x: np.ndarray, rotor_constants: np.ndarray,
                       rotor_speeds: np.ndarray) -> tuple:
    """The stub's attitude/rate loops and mixer (`inner_loop`) on the estimator state's attitude
    and rates (with `truth`: the true ones, as `GroundTruthEstimator` reports them), then the
    rotors' world wrench (`Simulation.step`'s `vehicle_wrench`, which also advances the speeds)."""
    if truth:
        q, rates, _, _, _ = truth_of_vector(x)
    else:
        q, rates = attitude_and_rates(est_state)
    u0, u1, u2, u3 = inner_loop(ctl, att_gains, rate_state, rate_gains, mix_constants, mix_state, q, rates,
                                yaw_rate_ff, dt_s, landed)
    return vehicle_wrench(x, rotor_constants, rotor_speeds, u0, u1, u2, u3, True)


class DirectBackend:
    """Simulation + SensorSuite + StubAutopilot per vehicle, stepped in-process."""

    name = "direct"

    def __init__(self, world: World, options: EnvOptions, *, start_altitude_m: float, takeoff: bool = False) -> None:
        self.estimator = options.estimator
        ground_truth = options.ground_truth
        seed = options.first_seed
        self.world = world
        self.num_drones = world.num_vehicles
        self.start_altitude_m = float(start_altitude_m)
        self.takeoff = takeoff
        """Every episode starts with a take-off (False: placed in the air, `in_air_start`)."""
        self.sim = Simulation(world, seed=seed, step_us=None, gui=options.uses_gui,
                              visual=options.render_mode is not None)  # world's step, as SimSession
        self.lidar = Lidar(self.sim, [v.lidar for v in world.vehicles])
        self.sensors = [SensorSuite(world.home, seed=sensor_seed(seed, i), step_us=self.sim.step_us)
                        for i in range(self.num_drones)]
        self.autopilots = [StubAutopilot(i, self._params(), ground_truth_estimate=ground_truth)
                           for i in range(self.num_drones)]
        # per vehicle, what turns its state into the autopilot's input frame
        self._frame_of = [s.truth_frame if ground_truth else s.sample for s in self.sensors]
        self._collisions = CollisionFlags(self.num_drones)
        self._velocities: list[tuple[float, float, float]] = [(0.0, 0.0, 0.0)] * self.num_drones
        self._yaws: list[float | None] = [None] * self.num_drones
        self._refresh_steps = max(1, self.steps_for(SETPOINT_PERIOD_S, exact=False))
        self.steps = 0
        self._closed = False
        # the fused loop's per-vehicle operands: vectors that live as long as their owners
        self.fused = True
        """Step with the fused loop (False: the class path, its bit-identical reference)."""
        self._lanes = [self._lane(i) for i in range(self.num_drones)]
        self._warm_up(self._lanes[0])

    # -- Backend API --------------------------------------------------------------------
    def reset(self, seed: int | None = None) -> Snapshot:
        seed = 0 if seed is None else int(seed)
        self.sim.reset(seed)
        self.lidar.reset()
        for i, suite in enumerate(self.sensors):
            suite.reset(sensor_seed(seed, i))
        for autopilot in self.autopilots:
            autopilot.reset()
        if not self.takeoff:
            place_hovering(self.sim, self.sensors, self.autopilots, self.start_altitude_m,
                           [self.sim.time_us] * self.num_drones)
        self._lanes = [self._lane(i) for i in range(self.num_drones)]  # the controllers are new objects
        self._velocities = [(0.0, 0.0, 0.0)] * self.num_drones
        self._yaws = [None] * self.num_drones
        if self.takeoff:
            self._hover_start()
        else:
            self._offboard_and_settle()
        self._collisions.clear()
        return self._snapshot()

    def fly(self, velocities_ned_m_s: Sequence[np.ndarray], duration_s: float,
            yaws_ned_rad: Sequence[float] | None = None) -> Snapshot:
        if len(velocities_ned_m_s) != self.num_drones:
            raise ValueError(f"expected {self.num_drones} velocities, got {len(velocities_ned_m_s)}")
        self._collisions.clear()
        self.set_velocities([tuple(float(c) for c in v) for v in velocities_ned_m_s],
                            None if yaws_ned_rad is None else [float(y) for y in yaws_ned_rad])
        self.run_steps(self.steps_for(duration_s))  # exact: the loader checked the task's spans
        return self._snapshot()

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self.sim.close()

    # -- the loop -------------------------------------------------------------------------
    def with_simulation(self, use):  # noqa: ANN001, ANN201 - see Backend.with_simulation
        """`use(simulation)`: the simulation runs in this thread, so it is always safe."""
        return use(self.sim)

    def steps_for(self, seconds: float, *, exact: bool = True) -> int:
        """Physics steps in `seconds` (`world.clock.whole_steps`, as the lockstep's run_for)."""
        return whole_steps(seconds, self.sim.step_us, exact=exact)

    def set_velocities(self, velocities: list[tuple[float, float, float]],
                       yaws_ned_rad: list[float] | None = None) -> None:
        """Give every autopilot its offboard velocity setpoint now (MAVSDK's first send), with a
        heading (NED yaw) per vehicle when given (else each keeps the heading it holds)."""
        self._velocities = velocities
        self._yaws = yaws_ned_rad if yaws_ned_rad is not None else [None] * self.num_drones
        for ap, v, yaw in zip(self.autopilots, velocities, self._yaws, strict=True):
            ap.set_velocity_setpoint_ned(v, yaw)

    def run_steps(self, steps: int, until: Callable[[], bool] | None = None) -> int:
        """Step `steps` times (or until `until()` holds after a step); returns steps taken.
        The fused loop unless `fused` is False: then the class path below (the reference the
        fused loop matches bit for bit; tests compare them)."""
        if self.fused:
            return self._run_fused(steps, until)
        sim, frame_of, autopilots = self.sim, self._frame_of, self.autopilots
        n = self.num_drones
        refresh = self._refresh_steps
        for k in range(steps):
            if k and k % refresh == 0:
                for ap, v, yaw in zip(autopilots, self._velocities, self._yaws, strict=True):
                    ap.set_velocity_setpoint_ned(v, yaw)
            time_us = sim.time_us
            commands: list[MotorCommand] = [
                autopilots[i].update(frame_of[i](sim.state(i), time_us)) for i in range(n)
            ]
            sim.step(commands)
            self.steps += 1
            if sim.has_collisions:  # cheap test first: collisions() copies its list
                for c in sim.collisions():
                    self._collisions.add(c)
            if until is not None and until():
                return k + 1
        return steps

    def _run_fused(self, steps: int, until: Callable[[], bool] | None) -> int:
        """`run_steps`: the fused loop (see the module docstring)."""
        stale = [False] * self.num_drones  # estimate objects behind their state (steady steps)
        try:
            return self._fused_steps(steps, until, stale)
        finally:
            self._refresh_estimates(stale)

    def _refresh_estimates(self, stale: list[bool]) -> None:
        """Bring the estimate objects of steady steps up to date (`SensorEstimator.refresh`)."""
        for i, behind in enumerate(stale):
            if behind:
                est = self.autopilots[i].estimator
                est.refresh(est.last_time_us)
                stale[i] = False

    def _fused_steps(self, steps: int, until: Callable[[], bool] | None, stale: list[bool]) -> int:
        sim, autopilots, lanes = self.sim, self.autopilots, self._lanes
        refresh = self._refresh_steps
        begin, push, finish = sim.begin_step, sim.push_wrench, sim.finish_step
        for k in range(steps):
            if k and k % refresh == 0:
                for ap, v, yaw in zip(autopilots, self._velocities, self._yaws, strict=True):
                    ap.set_velocity_setpoint_ned(v, yaw)
            time_us = sim.time_us
            begin()
            for (i, truth, x, rotor_k, speeds, suite, est, est_s, est_g, ap, ctl, att_g, rate_s, rate_g, mix_c,
                 mix_s, commander, plan, pc_s, pc_g) in lanes:
                if truth:
                    if est.has_origin:
                        e = est.finish(truth_estimate(x, est_s), time_us)
                        if commander.steady and ap.gains_current:  # the estimate is up to date: no refresh
                            status, force, torque = truth_vehicle_step(
                                x, est_s, time_us, plan, *ap.clock_us(), ctl, pc_s, pc_g, att_g, rate_s, rate_g,
                                mix_c, mix_s, rotor_k, speeds)
                            if status:
                                ap.flew_steady(time_us, status == 2, status != 3)
                                push(i, force, torque)
                                continue
                    else:  # the first step: the origin's geodetic position (Python, once)
                        e = est.update(suite.truth_frame(sim.state(i), time_us))
                else:
                    imu = suite.imu_noise  # SensorSuite.sample's order: IMU row, then mag/baro/GPS
                    row = imu.take_row()
                    mag_row, baro, gps = suite.slow_samples(x, time_us) if time_us >= suite.next_slow_us \
                        else (-1, None, None)
                    dt = est.step_dt(time_us)
                    if commander.steady and gps is None and ap.gains_current:
                        status, force, torque = vehicle_step(
                            x, imu.array, row, suite.mag_noise.array, mag_row, suite.constants, est_s, est_g, dt,
                            time_us, _NAN if baro is None else baro.pressure_hpa, plan, *ap.clock_us(), ctl, pc_s,
                            pc_g, att_g, rate_s, rate_g, mix_c, mix_s, rotor_k, speeds)
                        if status:
                            ap.flew_steady(time_us, status == 2, status != 3)
                            stale[i] = True
                            push(i, force, torque)
                            continue
                        e = est.finish(current_values(est_s, time_us), time_us, dt, None, None)
                    else:
                        e = est.finish(sense_and_estimate(x, imu.array, row, suite.mag_noise.array, mag_row,
                                                          suite.constants, est_s, est_g, dt, time_us),
                                       time_us, dt, gps, baro)
                    stale[i] = False
                dt_s = ap.prepare(e)
                if dt_s is None:  # motors off or idle: the command as `Simulation.step` applies it
                    command = ap.last_command
                    u0, u1, u2, u3 = command.controls
                    force, torque = vehicle_wrench(x, rotor_k, speeds, u0, u1, u2, u3, command.armed)
                else:
                    force, torque = control_and_rotors(ctl, att_g, rate_s, rate_g, mix_c, mix_s, est_s, truth,
                                                       ap.yaw_rate_ff, dt_s, ap.commander.landed, x, rotor_k, speeds)
                    ap.outputs_in_control()
                push(i, force, torque)
            finish()
            self.steps += 1
            if sim.has_collisions:
                for c in sim.collisions():
                    self._collisions.add(c)
            if until is not None:
                self._refresh_estimates(stale)
                if until():
                    return k + 1
        return steps

    def _lane(self, i: int) -> tuple:
        sim, ap, est = self.sim, self.autopilots[i], self.autopilots[i].estimator
        rotors = sim.rotors(i)
        gains = getattr(est, "gains", est.state)  # the ground-truth estimator has none (unused then)
        return (i, ap.ground_truth_estimate, sim.vehicle_vector(i), rotors.constants, rotors.speeds, self.sensors[i],
                est, est.state, gains, ap, ap.control, ap.attitude_control.gains, ap.rate_control.state,
                ap.rate_control.gains, ap.mixer.constants, ap.mixer.state, ap.commander, ap.commander.plan,
                ap.position_control.state, ap.position_control.gains)

    @staticmethod
    def _warm_up(lane: tuple) -> None:
        """Load the fused kernels now (scratch copies of the state), not at the first step."""
        (_, truth, x, rotor_k, speeds, suite, est, est_s, est_g, ap, ctl, att_g, rate_s, rate_g, mix_c,
         mix_s, commander, plan, pc_s, pc_g) = lane
        ap.refresh_gains()
        scratch = np.zeros(ESTIMATOR_STATE)  # a fresh sensor estimator: its first sample sets the attitude
        noise = np.zeros((1, 6))
        sense_and_estimate(x.copy(), noise, 0, noise[:, :3].copy(), -1, suite.constants, scratch,
                           np.zeros_like(est_g) if truth else est_g, 0.004, 4000)
        truth_estimate(x.copy(), np.ones(GROUND_TRUTH_STATE))
        control_and_rotors(ctl.copy(), att_g, rate_s.copy(), rate_g, mix_c, mix_s.copy(), scratch, truth, 0.0, 0.004,
                           False, x.copy(), rotor_k, speeds.copy())
        scratch_plan = plan.copy()
        scratch_plan[:] = np.nan  # no offboard or takeoff test, no descent: flies (on scratch copies)
        vehicle_step(x.copy(), noise, 0, noise[:, :3].copy(), -1, suite.constants, scratch.copy(),
                     np.zeros_like(est_g) if truth else est_g, 0.004, 4000, 1000.0, scratch_plan, -1, -1, ctl.copy(),
                     pc_s.copy(), pc_g, att_g, rate_s.copy(), rate_g, mix_c, mix_s.copy(), rotor_k, speeds.copy())
        truth_vehicle_step(x.copy(), np.ones(GROUND_TRUTH_STATE), 4000, scratch_plan, -1, -1, ctl.copy(), pc_s.copy(),
                           pc_g, att_g, rate_s.copy(), rate_g, mix_c, mix_s.copy(), rotor_k, speeds.copy())
        current_values(scratch, 4000)

    # -- episode start: the same sequence the `stub` backend sends through MAVSDK -------------
    def _hover_start(self) -> None:
        """Arm once the estimate allows, take off to the start altitude, offboard, settle."""
        start = EPISODE_START
        budget = self.steps_for(start.timeout_s, exact=False)
        poll = self.steps_for(start.arm_poll_s, exact=False)
        while not all(ap.arm() is CommandResult.ACCEPTED for ap in self.autopilots):
            budget -= self.run_steps(poll)
            if budget <= 0:
                raise BackendError("direct: vehicles never became armable (no position estimate)")
        for ap in self.autopilots:
            if ap.takeoff() is not CommandResult.ACCEPTED:
                raise BackendError(f"direct: vehicle {ap.instance} refused takeoff")
        budget -= self.run_steps(budget, until=self._takeoff_done)
        if not self._takeoff_done():
            raise BackendError(f"direct: takeoff to {self.start_altitude_m:g} m not done within "
                               f"{start.timeout_s:g} s of simulated time")
        self._offboard_and_settle()

    def _offboard_and_settle(self) -> None:
        """Hovering in HOLD (after the take-off, or placed there): offboard at zero velocity, settle."""
        self.set_velocities([(0.0, 0.0, 0.0)] * self.num_drones)
        for ap in self.autopilots:
            if ap.set_mode(MainMode.OFFBOARD, 0) is not CommandResult.ACCEPTED:
                raise BackendError(f"direct: vehicle {ap.instance} refused offboard")
        self.run_steps(self.steps_for(EPISODE_START.settle_s, exact=False))

    def _takeoff_done(self) -> bool:
        """The MAVSDK client's test: in the air, back in HOLD, within tolerance of the altitude."""
        for ap in self.autopilots:
            home = ap.home
            if home is None or ap.landed_state is not LandedState.IN_AIR:
                return False
            if ap.custom_mode != _HOLD_MODE:
                return False
            altitude = home.position_ned_m[2] - ap.estimate.position_ned_m[2]
            if abs(altitude - self.start_altitude_m) > EPISODE_START.takeoff_tolerance_m:
                return False
        return True

    # -- internals ------------------------------------------------------------------------------
    def _params(self) -> ParamTable:
        """The parameters the `stub` backend's autopilots get (px4_params/ at full speed)."""
        params = ParamTable(speed_factor=0.0)
        params.set("MIS_TAKEOFF_ALT", self.start_altitude_m)
        return params

    def _snapshot(self) -> Snapshot:
        layout = self.sim.layout
        goals = tuple(layout.goal_of(i) for i in range(self.num_drones))
        return Snapshot(
            time_us=self.sim.time_us,
            states=tuple(self.sim.state(i) for i in range(self.num_drones)),
            scans=tuple(self.lidar.scan()),
            collided=tuple(self._collisions.any),
            hit_obstacle=tuple(self._collisions.obstacle),
            goals=goals,  # type: ignore[arg-type]  # load_scenario checks every vehicle has a goal
            obstacles=layout.obstacles,
            start_delays_s=layout.start_delays_s,
            encounter=layout.encounter,
        )
