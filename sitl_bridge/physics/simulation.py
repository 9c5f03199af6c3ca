"""`Simulation`: a pybullet world stepped at a fixed integer-microsecond step, with vehicles
driven by motor commands, obstacles (static and moving) and per-step collision reports.

World frame ENU, body frame FLU (pybullet's); `VehicleState` offers NED/FRD views through
`sitl_bridge.frames`. Every pybullet call passes this simulation's client id, so several
simulations live in one process. Each vehicle's state is one float64 vector (`physics.state`
layout) written by the compiled `read_state` kernel and read by the rotor model's and the
sensors' kernels (`sitl_bridge.jit`); `step` is `begin_step`, `push_wrench` per vehicle and
`finish_step`, which the fused `direct` loop calls with the wrenches it computed itself.
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
from sitl_bridge.jit import kernel
from sitl_bridge.physics import iris
from sitl_bridge.physics import state as state_layout
from sitl_bridge.physics.bodies import create_ground, create_obstacle, create_vehicle
from sitl_bridge.physics.bullet import p
from sitl_bridge.physics.iris import IrisParams, RotorSet, rotor_update_speeds, rotor_wrench
from sitl_bridge.physics.movers import Patrol, RandomLegs, make_mover
from sitl_bridge.physics.state import (
    ACCEL,
    FORCE_FLU,
    OMEGA_FLU,
    OMEGA_WORLD,
    POS,
    QUAT,
    ROT,
    STATE_SIZE,
    VEL,
    Collision,
    MotorCommand,
    VehicleState,
)
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


@kernel(iris, state_layout)
def read_state(x: np.ndarray, inv_dt: float, gravity: float, px: float, py: float, pz: float, qx: float,
               qy: float, qz: float, qw: float, lx: float, ly: float, lz: float, ox: float, oy: float,
               oz: float) -> float:
    """Fold pybullet's pose and velocity (world ENU, quaternion x, y, z, w) into the state vector
    `x`: attitude, rotation matrix, acceleration over the step, specific force and body rates.
    Returns the speed before the step (m/s), or -1.0 (x untouched) when the state is not finite."""
    check = px + py + pz + lx + ly + lz
    if not -1e7 < check < 1e7:  # NaN fails too
        return -1.0
    vx0, vy0, vz0 = x[VEL], x[VEL + 1], x[VEL + 2]
    speed_before = math.sqrt(vx0 * vx0 + vy0 * vy0 + vz0 * vz0)
    xx, yy, zz, xy, xz, yz = qx * qx, qy * qy, qz * qz, qx * qy, qx * qz, qy * qz
    wx, wy, wz = qw * qx, qw * qy, qw * qz
    r00, r01, r02 = 1.0 - 2.0 * (yy + zz), 2.0 * (xy - wz), 2.0 * (xz + wy)
    r10, r11, r12 = 2.0 * (xy + wz), 1.0 - 2.0 * (xx + zz), 2.0 * (yz - wx)
    r20, r21, r22 = 2.0 * (xz - wy), 2.0 * (yz + wx), 1.0 - 2.0 * (xx + yy)
    ax, ay, az = (lx - vx0) * inv_dt, (ly - vy0) * inv_dt, (lz - vz0) * inv_dt
    fz_world = az + gravity
    x[POS], x[POS + 1], x[POS + 2] = px, py, pz
    x[QUAT], x[QUAT + 1], x[QUAT + 2], x[QUAT + 3] = qw, qx, qy, qz
    x[VEL], x[VEL + 1], x[VEL + 2] = lx, ly, lz
    x[ACCEL], x[ACCEL + 1], x[ACCEL + 2] = ax, ay, az
    # specific force and body rates: world vectors rotated into the body (R^T)
    x[FORCE_FLU] = r00 * ax + r10 * ay + r20 * fz_world
    x[FORCE_FLU + 1] = r01 * ax + r11 * ay + r21 * fz_world
    x[FORCE_FLU + 2] = r02 * ax + r12 * ay + r22 * fz_world
    x[OMEGA_FLU] = r00 * ox + r10 * oy + r20 * oz
    x[OMEGA_FLU + 1] = r01 * ox + r11 * oy + r21 * oz
    x[OMEGA_FLU + 2] = r02 * ox + r12 * oy + r22 * oz
    x[ROT], x[ROT + 1], x[ROT + 2], x[ROT + 3], x[ROT + 4] = r00, r01, r02, r10, r11
    x[ROT + 5], x[ROT + 6], x[ROT + 7], x[ROT + 8] = r12, r20, r21, r22
    x[OMEGA_WORLD], x[OMEGA_WORLD + 1], x[OMEGA_WORLD + 2] = ox, oy, oz
    return speed_before


@kernel(iris, state_layout)
def vehicle_wrench(x: np.ndarray, k: np.ndarray, speeds: np.ndarray, u0: float, u1: float, u2: float, u3: float,
                   armed: bool) -> tuple[Vec3, Vec3]:
    """The rotors' (force, torque) in world ENU at the centre of mass, from the current rotor
    speeds (`iris.rotor_wrench`) and the body velocity; then the speeds' update toward the
    motor inputs (`iris.rotor_update_speeds`). One physics step of `RotorSet.step` in world axes."""
    r = ROT
    vx, vy, vz = x[VEL], x[VEL + 1], x[VEL + 2]
    # body-frame velocity (R^T v) for rotor drag and the thrust fade
    fx, fy, fz, tx, ty, tz = rotor_wrench(k, speeds, x[r] * vx + x[r + 3] * vy + x[r + 6] * vz,
                                          x[r + 1] * vx + x[r + 4] * vy + x[r + 7] * vz,
                                          x[r + 2] * vx + x[r + 5] * vy + x[r + 8] * vz)
    rotor_update_speeds(k, speeds, u0, u1, u2, u3, armed)
    return ((x[r] * fx + x[r + 1] * fy + x[r + 2] * fz, x[r + 3] * fx + x[r + 4] * fy + x[r + 5] * fz,
             x[r + 6] * fx + x[r + 7] * fy + x[r + 8] * fz),
            (x[r] * tx + x[r + 1] * ty + x[r + 2] * tz, x[r + 3] * tx + x[r + 4] * ty + x[r + 5] * tz,
             x[r + 6] * tx + x[r + 7] * ty + x[r + 8] * tz))


_WARM = False


def _warm_up(v: _Vehicle) -> None:
    """Load (or compile) the step kernels once per process, on scratch copies, so that the
    first step is as fast as the others (numba's first use costs about a second)."""
    global _WARM
    if not _WARM:
        x, speeds = v.x.copy(), v.rotors.speeds.copy()
        vehicle_wrench(x, v.rotors.constants, speeds, 0.0, 0.0, 0.0, 0.0, False)
        read_state(x, 250.0, 9.8, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        _WARM = True


class _Vehicle:
    """Per-vehicle runtime state: the state vector `x` (see `physics.state`) and the position as
    pybullet returned it (a tuple: the contact pre-test reads it every step)."""

    __slots__ = ("index", "name", "body", "rotors", "x", "position", "on_ground", "cached")

    def __init__(self, index: int, name: str, rotors: RotorSet) -> None:
        self.index = index
        self.name = name
        self.rotors = rotors
        self.body = -1
        self.x = np.zeros(STATE_SIZE)
        self.position: Vec3 = (0.0, 0.0, 0.0)
        self.on_ground = False
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
        if self._vehicles:
            _warm_up(self._vehicles[0])

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
        self.begin_step()
        push = self.push_wrench
        for v, cmd in zip(vehicles, commands, strict=False):  # lengths checked above
            u0, u1, u2, u3 = cmd.controls
            rotors = v.rotors
            force, torque = vehicle_wrench(v.x, rotors.constants, rotors.speeds, float(u0), float(u1), float(u2),
                                           float(u3), bool(cmd.armed))
            push(v.index, force, torque)
        self.finish_step()

    def begin_step(self) -> None:
        """First part of `step`: place the moving obstacles for this step."""
        cid = self.client_id
        facings = self._mover_facings
        for k, (body, mover) in enumerate(self._movers):
            pose = mover.pose()
            # a mover turns only at a leg's end: reuse the last orientation while it flies straight
            yaw, pitch, facing = facings[k]
            if yaw != pose.yaw_rad or pitch != pose.pitch_rad:
                facing = self._facing(pose.yaw_rad, pose.pitch_rad)
                facings[k] = (pose.yaw_rad, pose.pitch_rad, facing)
            p.resetBasePositionAndOrientation(body, pose.position_m, facing, physicsClientId=cid)
            p.resetBaseVelocity(body, pose.velocity_m_s, (0.0, 0.0, 0.0), physicsClientId=cid)

    def push_wrench(self, vehicle: int, force_enu_n: Vec3, torque_enu_n_m: Vec3) -> None:
        """Second part of `step`, once per vehicle: apply the rotors' world-frame force and
        torque (`vehicle_wrench`, which also advanced the rotor speeds) at the centre of mass."""
        v = self._vehicles[vehicle]
        cid = self.client_id
        _apply_force(v.body, -1, force_enu_n, v.position, _WORLD_FRAME, physicsClientId=cid)
        _apply_torque(v.body, -1, torque_enu_n_m, _WORLD_FRAME, physicsClientId=cid)

    def finish_step(self) -> None:
        """Last part of `step`: the pybullet step, time, movers, every vehicle's state, collisions."""
        _step_simulation(physicsClientId=self.client_id)
        self.time_us += self.step_us
        for _, mover in self._movers:
            mover.advance(self.step_s)
        if self._collisions:
            self._collisions = []
        vehicles = self._vehicles
        if len(vehicles) == 1:  # the common case, without the lists below
            v = vehicles[0]
            speed = self._read_state(v)
            self._detect_collisions(v, speed, speed)
            return
        read_state = self._read_state
        speeds_before = [read_state(v) for v in vehicles]
        # all states first: the vehicle-vehicle test needs every vehicle's new position
        top_speed = max(speeds_before)
        detect = self._detect_collisions
        for v, speed in zip(vehicles, speeds_before, strict=False):  # same length
            detect(v, speed, top_speed)

    def state(self, vehicle: int) -> VehicleState:
        """The vehicle's state after the last step (or at spawn before the first step)."""
        v = self._vehicles[vehicle]
        if v.cached is None:
            v.cached = VehicleState._from_vector(v.x.copy(), tuple(v.rotors.speeds.tolist()), v.on_ground)
        return v.cached

    def vehicle_vector(self, vehicle: int) -> np.ndarray:
        """The vehicle's live state vector (`physics.state` layout), updated in place every
        step: for compiled per-step kernels (the fused `direct` loop). Do not modify it."""
        return self._vehicles[vehicle].x

    def rotors(self, vehicle: int) -> RotorSet:
        """The vehicle's rotor model (its `speeds` and `constants` vectors live as long as the simulation)."""
        return self._vehicles[vehicle].rotors

    def pose(self, vehicle: int) -> tuple[Vec3, tuple[float, float, float, float]]:
        """Fast path: (position ENU m, quaternion ENU/FLU (w, x, y, z)) as plain tuples."""
        v = self._vehicles[vehicle]
        return v.position, tuple(v.x[QUAT:QUAT + 4].tolist())  # type: ignore[return-value]

    def body_boxes(self, *, vehicles: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding boxes of every body but the ground (and but the vehicles unless
        `vehicles`) as pybullet has them now (margins included): an (n, 6) array of rows (min x,
        y, z, max x, y, z), and per row the vehicle it belongs to (-1: an obstacle). The static
        obstacles' boxes are the ones taken when the episode was built (they never move; with
        nothing else to add, the same read-only arrays every call); movers' and vehicles' are
        read now. For cheap tests of what a ray could hit (`sensors.ray_reach`); the ground is
        the plane z = 0 when `has_ground`."""
        static, static_owners = self._static_box_rows
        if not self._movers and not vehicles:
            return static, static_owners
        cid = self.client_id
        bodies = [body for body, _ in self._movers] + ([v.body for v in self._vehicles] if vehicles else [])
        rows = [(*lo, *hi) for lo, hi in (p.getAABB(body, physicsClientId=cid) for body in bodies)]
        owners = np.full(len(rows), -1, dtype=np.int64)
        if vehicles:
            owners[len(rows) - len(self._vehicles):] = np.arange(len(self._vehicles))
        return np.vstack((static, np.array(rows, dtype=float).reshape(-1, 6))), np.concatenate((static_owners, owners))

    @property
    def has_ground(self) -> bool:
        """Whether the world has its ground plane at z = 0."""
        return self._ground >= 0

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
            v.rotors.speeds_rad_s = rotor_speeds_rad_s
        self._init_state(v)
        v.x[VEL:VEL + 3] = velocity

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
        #: per mover: the (yaw, pitch) of its last orientation and that orientation (pybullet)
        self._mover_facings: list[tuple[float, float, tuple[float, float, float, float]]] = []
        self._mover_reaches: list[tuple[float, float, Patrol | RandomLegs]] = []
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
                self._mover_facings.append((math.nan, math.nan, (0.0, 0.0, 0.0, 1.0)))
                # its bounding radius and how far it can close in two steps (`_may_touch`)
                self._mover_reaches.append((_bounding_radius_m(placement.shape), 2.0 * mover.speed_m_s * self.step_s,
                                            mover))
            else:
                lo, hi = p.getAABB(body, physicsClientId=cid)
                self._static_boxes.append((*lo, *hi))
        static_rows = np.array(self._static_boxes, dtype=float).reshape(-1, 6)
        static_owners = np.full(len(static_rows), -1, dtype=np.int64)
        static_rows.setflags(write=False)
        static_owners.setflags(write=False)
        self._static_box_rows = (static_rows, static_owners)
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
        q = (orn[3], orn[0], orn[1], orn[2])
        x = v.x
        x[:] = 0.0
        x[POS:POS + 3] = pos
        x[QUAT:QUAT + 4] = q
        x[ROT:ROT + 9] = quat_to_matrix_t(q)
        x[FORCE_FLU:FORCE_FLU + 3] = quat_rotate_inverse_t(q, (0.0, 0.0, self.gravity_m_s2))
        v.position = pos
        v.on_ground = False
        v.cached = None

    def _read_state(self, v: _Vehicle) -> float:
        """Read the vehicle's new state from pybullet (`read_state`); the speed before the step."""
        cid = self.client_id
        pos, orn = _get_pose(v.body, physicsClientId=cid)
        lin, ang = _get_velocity(v.body, physicsClientId=cid)
        speed = read_state(v.x, self._inv_step_s, self.gravity_m_s2, *pos, *orn, *lin, *ang)
        if speed < 0.0:
            raise PhysicsError(f"vehicle {v.name}: state is no longer finite (position {pos}, velocity {lin})"
                               "; reset the simulation")
        v.position = pos
        v.cached = None
        return speed

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
        for radius, closing_m, mover in self._mover_reaches:
            mx, my, mz = mover.pose().position_m
            mover_reach = reach + radius + closing_m
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
                x, y = float(v.x[QUAT + 1]), float(v.x[QUAT + 2])
                cos_tilt = 1.0 - 2.0 * (x * x + y * y)  # body z axis . world up
                if speed_m_s <= self.world.physics.hard_ground_speed_m_s and cos_tilt >= self._cos_crash_tilt:
                    continue
            self._collisions.append(Collision(v.index, kind, name, speed_m_s, self.time_us))

    @staticmethod
    def _facing(yaw_rad: float, pitch_up_rad: float) -> tuple[float, float, float, float]:
        """pybullet (x, y, z, w) orientation facing along yaw, nose up by pitch (FLU: nose up is
        a negative rotation about the body's left axis)."""
        return quaternion_to_pybullet(quat_from_euler_t(0.0, -pitch_up_rad, yaw_rad))
