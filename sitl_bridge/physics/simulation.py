"""`Simulation`: a pybullet world stepped at a fixed integer-microsecond step, with vehicles
driven by motor commands, obstacles (static and moving) and per-step collision reports.

World frame ENU, body frame FLU (pybullet's); `VehicleState` offers NED/FRD views through
`sitl_bridge.frames`. Every pybullet call passes this simulation's client id, so several
simulations live in one process. The per-step path uses plain floats: numpy's per-call overhead
would cost more than the physics of one body.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import pybullet as p

from sitl_bridge.frames import (
    enu_to_ned_xyz,
    flu_to_frd_xyz,
    quat_enu_flu_to_ned_frd_t,
    quat_rotate_inverse_t,
    quat_to_euler_t,
    quat_to_matrix_t,
    quaternion_to_pybullet,
    yaw_quaternion_enu_flu,
)
from sitl_bridge.physics.bodies import create_ground, create_obstacle, create_vehicle
from sitl_bridge.physics.iris import IrisParams, RotorSet
from sitl_bridge.physics.movers import Patrol, RandomLegs, make_mover
from sitl_bridge.world.layout import Layout, realize
from sitl_bridge.world.schema import World

Vec3 = tuple[float, float, float]
_WORLD_FRAME = p.WORLD_FRAME


@dataclass(frozen=True)
class MotorCommand:
    """Motor inputs of one vehicle for one step (what HIL_ACTUATOR_CONTROLS carries)."""

    controls: tuple[float, float, float, float]  # PX4 motors 1..4 (quad-X order), each in [0, 1]
    armed: bool                                  # False -> rotors spin down to 0

    @staticmethod
    def disarmed() -> MotorCommand:
        """All motors off, disarmed."""
        return _DISARMED


_DISARMED = MotorCommand((0.0, 0.0, 0.0, 0.0), False)


@dataclass(frozen=True)
class Collision:
    """One contact reported for the last step.

    kind: "obstacle" (other = obstacle name), "vehicle" (other = the other vehicle's name) or
    "ground" (other = "ground"; only hard contacts: faster than the world's
    `hard_ground_speed_m_s` or tilted beyond `crash_tilt_deg`, so resting/landing is not one).
    """

    vehicle: int
    kind: str
    other: str
    speed_m_s: float
    time_us: int


def _readonly(values) -> np.ndarray:
    array = np.array(values, dtype=float)
    array.flags.writeable = False
    return array


class VehicleState:
    """Vehicle state after a step: world ENU, body FLU; NED/FRD views as properties.

    Immutable. The arrays are built on first access from the plain-float tuples in `raw`
    (position, quaternion, velocity, angular velocity, specific force, acceleration), which
    per-step consumers such as `SensorSuite` read directly to skip numpy.
    """

    def __init__(self, position_enu_m, quaternion_enu_flu, velocity_enu_m_s, angular_velocity_flu_rad_s,
                 specific_force_flu_m_s2, rotor_speeds_rad_s, acceleration_enu_m_s2=(0.0, 0.0, 0.0),
                 on_ground: bool = False) -> None:
        def floats(values) -> tuple[float, ...]:
            return tuple(float(c) for c in values)

        self.raw: tuple[tuple[float, ...], ...] = (
            floats(position_enu_m), floats(quaternion_enu_flu), floats(velocity_enu_m_s),
            floats(angular_velocity_flu_rad_s), floats(specific_force_flu_m_s2), floats(acceleration_enu_m_s2))
        self._rotor_speeds = floats(rotor_speeds_rad_s)
        self.on_ground = bool(on_ground)  # touching the ground plane this step

    @classmethod
    def _from_tuples(cls, raw: tuple, rotor_speeds: tuple[float, ...], on_ground: bool) -> VehicleState:
        state = cls.__new__(cls)
        state.raw = raw
        state._rotor_speeds = rotor_speeds
        state.on_ground = on_ground
        return state

    def __repr__(self) -> str:
        names = ("position_enu_m", "quaternion_enu_flu", "velocity_enu_m_s", "angular_velocity_flu_rad_s",
                 "specific_force_flu_m_s2", "acceleration_enu_m_s2")
        parts = [f"{n}={tuple(round(c, 4) for c in r)}" for n, r in zip(names, self.raw, strict=True)]
        return f"VehicleState({', '.join(parts)}, on_ground={self.on_ground})"

    # -- contract fields (ENU / FLU) --------------------------------------------------------
    @cached_property
    def position_enu_m(self) -> np.ndarray:
        return _readonly(self.raw[0])

    @cached_property
    def quaternion_enu_flu(self) -> np.ndarray:
        """(w, x, y, z), rotates FLU vectors into ENU."""
        return _readonly(self.raw[1])

    @cached_property
    def velocity_enu_m_s(self) -> np.ndarray:
        return _readonly(self.raw[2])

    @cached_property
    def angular_velocity_flu_rad_s(self) -> np.ndarray:
        return _readonly(self.raw[3])

    @cached_property
    def specific_force_flu_m_s2(self) -> np.ndarray:
        """What an ideal accelerometer reads (at rest: +g along body up)."""
        return _readonly(self.raw[4])

    @cached_property
    def acceleration_enu_m_s2(self) -> np.ndarray:
        """Coordinate acceleration over the last step (extension of the contract)."""
        return _readonly(self.raw[5])

    @cached_property
    def rotor_speeds_rad_s(self) -> np.ndarray:
        """PX4 motor order 1..4."""
        return _readonly(self._rotor_speeds)

    # -- PX4 views (NED / FRD) ---------------------------------------------------------------
    @cached_property
    def position_ned_m(self) -> np.ndarray:
        return _readonly(enu_to_ned_xyz(*self.raw[0]))

    @cached_property
    def velocity_ned_m_s(self) -> np.ndarray:
        return _readonly(enu_to_ned_xyz(*self.raw[2]))

    @cached_property
    def acceleration_ned_m_s2(self) -> np.ndarray:
        return _readonly(enu_to_ned_xyz(*self.raw[5]))

    @cached_property
    def quaternion_ned_frd(self) -> np.ndarray:
        """(w, x, y, z), rotates FRD vectors into NED (PX4's attitude)."""
        return _readonly(quat_enu_flu_to_ned_frd_t(self.raw[1]))

    @cached_property
    def euler_ned_frd_rad(self) -> np.ndarray:
        """(roll, pitch, yaw) as PX4 reports them (yaw from north, clockwise)."""
        return _readonly(quat_to_euler_t(quat_enu_flu_to_ned_frd_t(self.raw[1])))

    @cached_property
    def angular_velocity_frd_rad_s(self) -> np.ndarray:
        return _readonly(flu_to_frd_xyz(*self.raw[3]))

    @cached_property
    def specific_force_frd_m_s2(self) -> np.ndarray:
        return _readonly(flu_to_frd_xyz(*self.raw[4]))


class _Vehicle:
    """Per-vehicle runtime state kept as plain floats for the step loop."""

    __slots__ = ("index", "name", "body", "rotors", "position", "q_wxyz", "rotation", "velocity", "angular_world",
                 "acceleration", "specific_force_flu", "angular_flu", "on_ground", "cached")

    def __init__(self, index: int, name: str, rotors: RotorSet) -> None:
        self.index = index
        self.name = name
        self.rotors = rotors
        self.body = -1
        self.cached: VehicleState | None = None


class Simulation:
    """A pybullet world with several vehicles, stepped in lockstep by its callers.

    Args:
        world: the loaded world (see `sitl_bridge.world.load_world`).
        seed: seeds the layout randomisation and the movers; same world + seed -> same run.
        step_us: physics step in integer microseconds (default 4000 = PX4's 250 Hz lockstep);
            None takes the world's `physics.step_us`.
        gui: open pybullet's GUI instead of DIRECT (one GUI per process).
    """

    def __init__(self, world: World, *, seed: int = 0, step_us: int | None = 4000, gui: bool = False,
                 params: IrisParams | None = None) -> None:
        self.world = world
        self.step_us = int(step_us if step_us is not None else world.physics.step_us)
        if self.step_us <= 0:
            raise ValueError(f"step_us must be positive, got {self.step_us}")
        self.step_s = self.step_us * 1e-6
        self._inv_step_s = 1.0 / self.step_s
        self.gui = gui
        self.params = params or IrisParams()
        self.gravity_m_s2 = world.physics.gravity_m_s2
        self.num_vehicles = world.num_vehicles
        self.vehicle_names = tuple(v.name for v in world.vehicles)
        self.time_us = 0
        self.client_id = p.connect(p.GUI if gui else p.DIRECT)
        self._closed = False
        self._vehicles = [_Vehicle(i, v.name, RotorSet(self.params, self.step_s))
                          for i, v in enumerate(world.vehicles)]
        self._collisions: list[Collision] = []
        self._rng = np.random.default_rng(seed)
        self._cos_crash_tilt = math.cos(math.radians(world.physics.crash_tilt_deg))
        self._build()

    # -- public API -------------------------------------------------------------------------
    @property
    def time_s(self) -> float:
        """Simulated time in seconds."""
        return self.time_us * 1e-6

    @property
    def layout(self) -> Layout:
        """This episode's drawn layout: spawns, goals (per vehicle) and obstacle placements."""
        return self._layout

    @property
    def vehicle_bodies(self) -> tuple[int, ...]:
        """pybullet body ids of the vehicles (stable across resets)."""
        return tuple(v.body for v in self._vehicles)

    @property
    def obstacle_bodies(self) -> dict[str, int]:
        """pybullet body id of each obstacle by name."""
        return dict(self._obstacle_bodies)

    def step(self, commands: Sequence[MotorCommand]) -> None:
        """Advance one physics step: movers, rotor forces, pybullet step, state, collisions."""
        vehicles = self._vehicles
        if len(commands) != len(vehicles):
            raise ValueError(f"expected {len(vehicles)} motor commands, got {len(commands)}")
        cid = self.client_id
        for body, mover in self._movers:
            pose = mover.pose()
            p.resetBasePositionAndOrientation(body, pose.position_m, self._facing(pose.yaw_rad, pose.pitch_rad),
                                              physicsClientId=cid)
            p.resetBaseVelocity(body, pose.velocity_m_s, (0.0, 0.0, 0.0), physicsClientId=cid)
        for v, cmd in zip(vehicles, commands, strict=True):
            r00, r01, r02, r10, r11, r12, r20, r21, r22 = v.rotation
            vx, vy, vz = v.velocity
            # body-frame velocity (R^T v) for rotor drag and the thrust fade
            (fx, fy, fz), (tx, ty, tz) = v.rotors.step(
                cmd.controls, cmd.armed,
                (r00 * vx + r10 * vy + r20 * vz, r01 * vx + r11 * vy + r21 * vz, r02 * vx + r12 * vy + r22 * vz))
            p.applyExternalForce(v.body, -1, (r00 * fx + r01 * fy + r02 * fz, r10 * fx + r11 * fy + r12 * fz,
                                              r20 * fx + r21 * fy + r22 * fz), v.position, _WORLD_FRAME,
                                 physicsClientId=cid)
            p.applyExternalTorque(v.body, -1, (r00 * tx + r01 * ty + r02 * tz, r10 * tx + r11 * ty + r12 * tz,
                                               r20 * tx + r21 * ty + r22 * tz), _WORLD_FRAME, physicsClientId=cid)
        p.stepSimulation(physicsClientId=cid)
        self.time_us += self.step_us
        for _, mover in self._movers:
            mover.advance(self.step_s)
        self._collisions = []
        for v in vehicles:
            speed_before = math.sqrt(v.velocity[0] ** 2 + v.velocity[1] ** 2 + v.velocity[2] ** 2)
            self._read_state(v)
            self._detect_collisions(v, speed_before)

    def state(self, vehicle: int) -> VehicleState:
        """The vehicle's state after the last step (or at spawn before the first step)."""
        v = self._vehicles[vehicle]
        if v.cached is None:
            v.cached = VehicleState._from_tuples(
                (v.position, v.q_wxyz, v.velocity, v.angular_flu, v.specific_force_flu, v.acceleration),
                tuple(v.rotors.speeds_rad_s), v.on_ground)
        return v.cached

    def pose(self, vehicle: int) -> tuple[Vec3, tuple[float, float, float, float]]:
        """Fast path: (position ENU m, quaternion ENU/FLU (w, x, y, z)) as plain tuples."""
        v = self._vehicles[vehicle]
        return v.position, v.q_wxyz

    def collisions(self) -> list[Collision]:
        """Collisions detected during the last step."""
        return list(self._collisions)

    def reset(self, seed: int | None = None) -> None:
        """Back to time 0 with a freshly drawn layout (re-seeded when `seed` is given).

        The pybullet world is rebuilt from scratch in the same order, so a reset with seed s
        behaves exactly like a new `Simulation(world, seed=s)`; body ids stay the same.
        """
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        self._build()

    def place_vehicle(self, vehicle: int, position_enu_m: Sequence[float], yaw_enu_rad: float = 0.0,
                      quaternion_enu_flu: Sequence[float] | None = None, *,
                      velocity_enu_m_s: Sequence[float] = (0.0, 0.0, 0.0),
                      rotor_speeds_rad_s: Sequence[float] | None = None) -> None:
        """Teleport a vehicle (for episode starts in the air, tests and scripted setups).

        The attitude is `quaternion_enu_flu` when given, else level at `yaw_enu_rad`. The body
        gets `velocity_enu_m_s` and no rotation; the rotors keep their speed unless
        `rotor_speeds_rad_s` is given (e.g. `hover_rotor_speeds_rad_s()`, to start hovering
        without a spool-up sag).
        """
        v = self._vehicles[vehicle]
        q = tuple(float(c) for c in quaternion_enu_flu) if quaternion_enu_flu is not None \
            else yaw_quaternion_enu_flu(yaw_enu_rad)
        velocity = tuple(float(c) for c in velocity_enu_m_s)
        p.resetBasePositionAndOrientation(v.body, [float(c) for c in position_enu_m], quaternion_to_pybullet(q),
                                          physicsClientId=self.client_id)
        p.resetBaseVelocity(v.body, velocity, (0.0, 0.0, 0.0), physicsClientId=self.client_id)
        if rotor_speeds_rad_s is not None:
            v.rotors.speeds_rad_s = [float(w) for w in rotor_speeds_rad_s]
        self._init_state(v)
        v.velocity = velocity

    def hover_rotor_speeds_rad_s(self) -> list[float]:
        """Rotor speeds whose thrust balances the weight (for `place_vehicle`)."""
        return [self.params.hover_rotor_speed_rad_s(self.gravity_m_s2)] * 4

    def close(self) -> None:
        """Disconnect from pybullet (idempotent)."""
        if not self._closed:
            self._closed = True
            with contextlib.suppress(p.error):
                p.disconnect(physicsClientId=self.client_id)

    def __enter__(self) -> Simulation:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        # a forgotten close() must not leak a pybullet client
        if not getattr(self, "_closed", True):
            self.close()

    # -- internals --------------------------------------------------------------------------
    def _build(self) -> None:
        cid = self.client_id
        world = self.world
        self.time_us = 0
        self._collisions = []
        self._layout = realize(world, self._rng)
        mover_rng = np.random.default_rng(int(self._rng.integers(2**63)))
        p.resetSimulation(physicsClientId=cid)
        p.setGravity(0.0, 0.0, -self.gravity_m_s2, physicsClientId=cid)
        p.setPhysicsEngineParameter(fixedTimeStep=self.step_s, numSubSteps=0,
                                    numSolverIterations=world.physics.solver_iterations,
                                    deterministicOverlappingPairs=1, physicsClientId=cid)
        self._body_kind: dict[int, tuple[str, str]] = {}
        self._ground = create_ground(cid, visual=self.gui) if world.ground else -2
        self._body_kind[self._ground] = ("ground", "ground")
        self._obstacle_bodies: dict[str, int] = {}
        self._movers: list[tuple[int, Patrol | RandomLegs]] = []
        for placement in self._layout.obstacles:
            spec = placement.spec
            mover = make_mover(spec.mover, placement.position_m) if spec.mover is not None else None
            position, yaw = placement.position_m, placement.yaw_rad
            if mover is not None:
                mover.reset(mover_rng)
                pose = mover.pose()
                position, yaw = pose.position_m, pose.yaw_rad
            body = create_obstacle(cid, placement.shape, position, yaw, spec.color_rgba,
                                   mass_kg=spec.mass_kg if mover is not None else 0.0, visual=self.gui)
            self._obstacle_bodies[spec.name] = body
            self._body_kind[body] = ("obstacle", spec.name)
            if mover is not None:
                self._movers.append((body, mover))
        for v in self._vehicles:
            v.rotors.reset()
            v.body = create_vehicle(cid, self.params, self._layout.spawn_positions_m[v.index],
                                    self._layout.spawn_yaws_rad[v.index], visual=self.gui)
            self._body_kind[v.body] = ("vehicle", v.name)
            self._init_state(v)

    def _init_state(self, v: _Vehicle) -> None:
        """State at rest (no step taken yet): accelerometer reads +g along world up."""
        pos, orn = p.getBasePositionAndOrientation(v.body, physicsClientId=self.client_id)
        v.position = pos
        v.q_wxyz = (orn[3], orn[0], orn[1], orn[2])
        v.rotation = quat_to_matrix_t(v.q_wxyz)
        v.velocity = (0.0, 0.0, 0.0)
        v.angular_world = (0.0, 0.0, 0.0)
        v.angular_flu = (0.0, 0.0, 0.0)
        v.acceleration = (0.0, 0.0, 0.0)
        v.specific_force_flu = quat_rotate_inverse_t(v.q_wxyz, (0.0, 0.0, self.gravity_m_s2))
        v.on_ground = False
        v.cached = None

    def _read_state(self, v: _Vehicle) -> None:
        cid = self.client_id
        pos, orn = p.getBasePositionAndOrientation(v.body, physicsClientId=cid)
        lin, ang = p.getBaseVelocity(v.body, physicsClientId=cid)
        q = (orn[3], orn[0], orn[1], orn[2])
        rotation = quat_to_matrix_t(q)
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = rotation
        inv_dt = self._inv_step_s
        old = v.velocity
        ax, ay, az = (lin[0] - old[0]) * inv_dt, (lin[1] - old[1]) * inv_dt, (lin[2] - old[2]) * inv_dt
        fz_world = az + self.gravity_m_s2
        wx, wy, wz = ang
        v.position = pos
        v.q_wxyz = q
        v.rotation = rotation
        v.velocity = lin
        v.angular_world = ang
        v.acceleration = (ax, ay, az)
        # specific force and body rates: world vectors rotated into the body (R^T)
        v.specific_force_flu = (r00 * ax + r10 * ay + r20 * fz_world, r01 * ax + r11 * ay + r21 * fz_world,
                                r02 * ax + r12 * ay + r22 * fz_world)
        v.angular_flu = (r00 * wx + r10 * wy + r20 * wz, r01 * wx + r11 * wy + r21 * wz,
                         r02 * wx + r12 * wy + r22 * wz)
        v.cached = None

    def _detect_collisions(self, v: _Vehicle, speed_m_s: float) -> None:
        contacts = p.getContactPoints(bodyA=v.body, physicsClientId=self.client_id)
        v.on_ground = False
        if not contacts:
            return
        seen: set[int] = set()
        for contact in contacts:
            other = contact[2]
            if other in seen:
                continue
            seen.add(other)
            kind, name = self._body_kind.get(other, ("obstacle", f"body{other}"))
            if kind == "ground":
                v.on_ground = True
                w, x, y, _ = v.q_wxyz
                cos_tilt = 1.0 - 2.0 * (x * x + y * y)  # body z axis . world up
                if speed_m_s <= self.world.physics.hard_ground_speed_m_s and cos_tilt >= self._cos_crash_tilt:
                    continue
            self._collisions.append(Collision(v.index, kind, name, speed_m_s, self.time_us))

    @staticmethod
    def _facing(yaw_rad: float, pitch_up_rad: float) -> tuple[float, float, float, float]:
        """pybullet (x, y, z, w) orientation facing along yaw, nose up by pitch (FLU body)."""
        cy, sy = math.cos(yaw_rad * 0.5), math.sin(yaw_rad * 0.5)
        cp, sp = math.cos(-pitch_up_rad * 0.5), math.sin(-pitch_up_rad * 0.5)
        # q = q_yaw(z) * q_pitch(y)
        return (-sy * sp, cy * sp, sy * cp, cy * cp)
