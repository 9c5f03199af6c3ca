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

import numpy as np

from sitl_bridge.frames import (
    quat_from_euler_t,
    quat_rotate_inverse_t,
    quat_to_matrix_t,
    quaternion_to_pybullet,
    yaw_quaternion_enu_flu,
)
from sitl_bridge.physics.bodies import create_ground, create_obstacle, create_vehicle
from sitl_bridge.physics.bullet import p
from sitl_bridge.physics.iris import IrisParams, RotorSet
from sitl_bridge.physics.movers import Patrol, RandomLegs, make_mover
from sitl_bridge.physics.state import Collision, MotorCommand, VehicleState
from sitl_bridge.world.layout import Layout, realize
from sitl_bridge.world.schema import Shape, World

__all__ = ["Collision", "MotorCommand", "PhysicsError", "Simulation", "VehicleState"]

Vec3 = tuple[float, float, float]
_WORLD_FRAME = p.WORLD_FRAME
# the per-step pybullet calls, looked up once (module attribute look-ups add up at 250 Hz)
_apply_force = p.applyExternalForce
_apply_torque = p.applyExternalTorque
_step_simulation = p.stepSimulation
_get_pose = p.getBasePositionAndOrientation
_get_velocity = p.getBaseVelocity
#: A spawn whose body centre is less than this above resting height starts resting on the ground.
GROUND_SNAP_M = 0.02
#: Physics steps run before time 0 so vehicles spawned on the ground start settled on it.
SETTLE_STEPS = 100


class PhysicsError(RuntimeError):
    """The physics blew up (non-finite state); the simulation must be reset."""


def _bounding_radius_m(shape: Shape) -> float:
    """Radius of a sphere around the shape's centre that contains it."""
    if shape.kind == "sphere":
        return shape.radius_m or 0.0
    if shape.kind == "cylinder":
        return math.hypot(shape.radius_m or 0.0, (shape.height_m or 0.0) / 2.0)
    sx, sy, sz = shape.size_m or (0.0, 0.0, 0.0)
    return 0.5 * math.sqrt(sx * sx + sy * sy + sz * sz)  # a mesh's size is its scaled bounding box


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
        step_us: physics step in integer microseconds; None (default) takes the world's
            `physics.step_us`, itself 4000 (PX4's 250 Hz lockstep) unless the world says otherwise.
        gui: open pybullet's GUI instead of DIRECT (one GUI per process).
        visual: give the bodies coloured visual shapes (for offscreen pictures, see
            `physics.render`); always on with the GUI, off otherwise (nothing to draw: faster).
    """

    def __init__(self, world: World, *, seed: int = 0, step_us: int | None = None, gui: bool = False,
                 params: IrisParams | None = None, visual: bool = False) -> None:
        self.world = world
        self.step_us = int(step_us if step_us is not None else world.physics.step_us)
        if self.step_us <= 0:
            raise ValueError(f"step_us must be positive, got {self.step_us}")
        self.step_s = self.step_us * 1e-6
        self._inv_step_s = 1.0 / self.step_s
        self.gui = gui
        self.visual = gui or visual
        self.build_count = 0
        """How many times the world was (re)built in pybullet (renderers re-add their markers)."""
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
        movers = self._movers
        for body, mover in movers:
            pose = mover.pose()
            p.resetBasePositionAndOrientation(body, pose.position_m, self._facing(pose.yaw_rad, pose.pitch_rad),
                                              physicsClientId=cid)
            p.resetBaseVelocity(body, pose.velocity_m_s, (0.0, 0.0, 0.0), physicsClientId=cid)
        speeds_before = []
        for v, cmd in zip(vehicles, commands, strict=False):  # lengths checked above
            r00, r01, r02, r10, r11, r12, r20, r21, r22 = v.rotation
            vx, vy, vz = v.velocity
            speeds_before.append(math.sqrt(vx * vx + vy * vy + vz * vz))  # for the collision report
            # body-frame velocity (R^T v) for rotor drag and the thrust fade; the wrench from the
            # current rotor speeds, then the speeds' update (RotorSet.step, one call less)
            rotors = v.rotors
            (fx, fy, fz), (tx, ty, tz) = rotors.wrench(
                (r00 * vx + r10 * vy + r20 * vz, r01 * vx + r11 * vy + r21 * vz, r02 * vx + r12 * vy + r22 * vz))
            rotors.update_speeds(cmd.controls, cmd.armed)
            body = v.body
            _apply_force(body, -1, (r00 * fx + r01 * fy + r02 * fz, r10 * fx + r11 * fy + r12 * fz,
                                    r20 * fx + r21 * fy + r22 * fz), v.position, _WORLD_FRAME, physicsClientId=cid)
            _apply_torque(body, -1, (r00 * tx + r01 * ty + r02 * tz, r10 * tx + r11 * ty + r12 * tz,
                                     r20 * tx + r21 * ty + r22 * tz), _WORLD_FRAME, physicsClientId=cid)
        _step_simulation(physicsClientId=cid)
        self.time_us += self.step_us
        for _, mover in movers:
            mover.advance(self.step_s)
        if self._collisions:
            self._collisions = []
        read_state = self._read_state
        for v in vehicles:
            read_state(v)
        # all states first: the vehicle-vehicle test needs every vehicle's new position
        top_speed = max(speeds_before)
        detect = self._detect_collisions
        for v, speed in zip(vehicles, speeds_before, strict=False):  # same length
            detect(v, speed, top_speed)

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

    @property
    def has_collisions(self) -> bool:
        """Whether the last step detected any collision (no list copy: for per-step loops)."""
        return bool(self._collisions)

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
        # a forgotten close() must not leak a pybullet client (nor fail at interpreter exit)
        if not getattr(self, "_closed", True):
            with contextlib.suppress(Exception):
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
        self.build_count += 1
        p.setGravity(0.0, 0.0, -self.gravity_m_s2, physicsClientId=cid)
        p.setPhysicsEngineParameter(fixedTimeStep=self.step_s, numSubSteps=0,
                                    numSolverIterations=world.physics.solver_iterations,
                                    deterministicOverlappingPairs=0, physicsClientId=cid)
        self._body_kind: dict[int, tuple[str, str]] = {}
        self._ground = create_ground(cid, visual=self.visual) if world.ground else -2
        self._body_kind[self._ground] = ("ground", "ground")
        self._obstacle_bodies: dict[str, int] = {}
        self._movers: list[tuple[int, Patrol | RandomLegs]] = []
        self._mover_radii: list[float] = []
        self._static_boxes: list[tuple[float, ...]] = []
        self._vehicle_radius_m = 0.5 * math.sqrt(sum(s * s for s in self.params.collision_box_m))
        for placement in self._layout.obstacles:
            spec = placement.spec
            mover = make_mover(spec.mover, placement.position_m) if spec.mover is not None else None
            position, yaw = placement.position_m, placement.yaw_rad
            if mover is not None:
                mover.reset(mover_rng)
                pose = mover.pose()
                position, yaw = pose.position_m, pose.yaw_rad
            body = create_obstacle(cid, placement.shape, position, yaw, spec.color_rgba,
                                   mass_kg=spec.mass_kg if mover is not None else 0.0, visual=self.visual)
            self._obstacle_bodies[spec.name] = body
            self._body_kind[body] = ("obstacle", spec.name)
            if mover is not None:
                self._movers.append((body, mover))
                self._mover_radii.append(_bounding_radius_m(placement.shape))
            else:
                lo, hi = p.getAABB(body, physicsClientId=cid)
                self._static_boxes.append((*lo, *hi))
        rest_z = self.params.collision_box_m[2] / 2.0
        on_ground = []
        for v in self._vehicles:
            v.rotors.reset()
            x, y, z = self._layout.spawn_positions_m[v.index]
            grounded = world.ground and z < rest_z + GROUND_SNAP_M
            on_ground.append(grounded)
            v.body = create_vehicle(cid, self.params, (x, y, rest_z if grounded else z),
                                    self._layout.spawn_yaws_rad[v.index], visual=self.visual)
            self._body_kind[v.body] = ("vehicle", v.name)
        if any(on_ground):
            self._settle(on_ground)
        for v in self._vehicles:
            self._init_state(v)

    def _settle(self, on_ground: list[bool]) -> None:
        """Let grounded vehicles sink into their contacts before time 0, so the first sensor
        frames read a vehicle at rest (-g, no touchdown spike that PX4's checks would see)."""
        cid = self.client_id
        for _ in range(SETTLE_STEPS):
            p.stepSimulation(physicsClientId=cid)
        for v, grounded in zip(self._vehicles, on_ground, strict=True):
            if grounded:
                p.resetBaseVelocity(v.body, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), physicsClientId=cid)
            else:  # vehicles spawned in the air start where they were spawned
                spawn = self._layout.spawn_positions_m[v.index]
                orientation = quaternion_to_pybullet(yaw_quaternion_enu_flu(self._layout.spawn_yaws_rad[v.index]))
                p.resetBasePositionAndOrientation(v.body, spawn, orientation, physicsClientId=cid)
                p.resetBaseVelocity(v.body, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), physicsClientId=cid)
        for body, mover in self._movers:  # movers do not move before time 0
            pose = mover.pose()
            p.resetBasePositionAndOrientation(body, pose.position_m, self._facing(pose.yaw_rad, pose.pitch_rad),
                                              physicsClientId=cid)

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
        pos, orn = _get_pose(v.body, physicsClientId=cid)
        lin, ang = _get_velocity(v.body, physicsClientId=cid)
        check = pos[0] + pos[1] + pos[2] + lin[0] + lin[1] + lin[2]
        if not -1e7 < check < 1e7:  # NaN fails too
            raise PhysicsError(f"vehicle {v.name}: state is no longer finite (position {pos}, velocity {lin})"
                               "; reset the simulation")
        x, y, z, w = orn
        # quat_to_matrix_t written out (once per vehicle per step)
        xx, yy, zz, xy, xz, yz, wx, wy, wz = x * x, y * y, z * z, x * y, x * z, y * z, w * x, w * y, w * z
        rotation = (r00, r01, r02, r10, r11, r12, r20, r21, r22) = (
            1.0 - 2.0 * (yy + zz), 2.0 * (xy - wz), 2.0 * (xz + wy),
            2.0 * (xy + wz), 1.0 - 2.0 * (xx + zz), 2.0 * (yz - wx),
            2.0 * (xz - wy), 2.0 * (yz + wx), 1.0 - 2.0 * (xx + yy))
        inv_dt = self._inv_step_s
        old = v.velocity
        ax, ay, az = (lin[0] - old[0]) * inv_dt, (lin[1] - old[1]) * inv_dt, (lin[2] - old[2]) * inv_dt
        fz_world = az + self.gravity_m_s2
        ox, oy, oz = ang
        v.position = pos
        v.q_wxyz = (w, x, y, z)
        v.rotation = rotation
        v.velocity = lin
        v.angular_world = ang
        v.acceleration = (ax, ay, az)
        # specific force and body rates: world vectors rotated into the body (R^T)
        v.specific_force_flu = (r00 * ax + r10 * ay + r20 * fz_world, r01 * ax + r11 * ay + r21 * fz_world,
                                r02 * ax + r12 * ay + r22 * fz_world)
        v.angular_flu = (r00 * ox + r10 * oy + r20 * oz, r01 * ox + r11 * oy + r21 * oz,
                         r02 * ox + r12 * oy + r22 * oz)
        v.cached = None

    def _may_touch(self, v: _Vehicle, margin_m: float, vehicle_margin_m: float) -> bool:
        """Cheap bounding-volume test: could the vehicle touch anything? (getContactPoints is a
        server round trip costing as much as a third of a physics step; skip it in free air)."""
        x, y, z = v.position
        reach = self._vehicle_radius_m + margin_m
        if z < reach and self._ground >= 0:
            return True
        for x0, y0, z0, x1, y1, z1 in self._static_boxes:
            if x0 - reach < x < x1 + reach and y0 - reach < y < y1 + reach and z0 - reach < z < z1 + reach:
                return True
        pair_reach = 2.0 * self._vehicle_radius_m + vehicle_margin_m
        for other in self._vehicles:
            if other is not v:
                ox, oy, oz = other.position
                if (ox - x) ** 2 + (oy - y) ** 2 + (oz - z) ** 2 < pair_reach * pair_reach:
                    return True
        for radius, (_, mover) in zip(self._mover_radii, self._movers, strict=True):
            pose = mover.pose()
            mx, my, mz = pose.position_m
            mover_reach = reach + radius + 2.0 * mover.speed_m_s * self.step_s
            if (mx - x) ** 2 + (my - y) ** 2 + (mz - z) ** 2 < mover_reach * mover_reach:
                return True
        return False

    def _detect_collisions(self, v: _Vehicle, speed_m_s: float, top_speed_m_s: float) -> None:
        v.on_ground = False
        # margins: contact threshold plus how far the bodies can close in one step
        closing_m = 2.0 * self.step_s
        if not self._may_touch(v, 0.1 + closing_m * speed_m_s, 0.1 + closing_m * (speed_m_s + top_speed_m_s)):
            return
        contacts = p.getContactPoints(bodyA=v.body, physicsClientId=self.client_id)
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
        """pybullet (x, y, z, w) orientation facing along yaw, nose up by pitch (FLU: nose up is
        a negative rotation about the body's left axis)."""
        return quaternion_to_pybullet(quat_from_euler_t(0.0, -pitch_up_rad, yaw_rad))
