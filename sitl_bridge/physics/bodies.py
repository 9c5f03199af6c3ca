"""Create pybullet bodies (ground, obstacles, vehicles) on an explicit client."""

from __future__ import annotations

from sitl_bridge.frames import quat_from_euler_t, quaternion_to_pybullet, yaw_quaternion_enu_flu
from sitl_bridge.physics.bullet import p
from sitl_bridge.physics.iris import IrisParams
from sitl_bridge.world.schema import Shape, Vec3


def create_ground(client: int, *, visual: bool = False) -> int:
    """An infinite static plane at z = 0 (a thin visual box in the GUI)."""
    shape = p.createCollisionShape(p.GEOM_PLANE, physicsClientId=client)
    vis = -1
    if visual:
        vis = p.createVisualShape(p.GEOM_BOX, halfExtents=(100.0, 100.0, 0.001), rgbaColor=(0.35, 0.45, 0.3, 1.0),
                                  physicsClientId=client)
    return p.createMultiBody(0.0, shape, vis, physicsClientId=client)


def _shapes(client: int, shape: Shape, color: tuple[float, ...], visual: bool, static: bool) -> tuple[int, int]:
    """(collision shape id, visual shape id or -1) for one obstacle shape."""
    kind = shape.kind
    if kind == "wall":
        boxes = shape.wall_boxes()
        types = [p.GEOM_BOX] * len(boxes)
        halves = [list(h) for h, _ in boxes]
        offsets = [list(o) for _, o in boxes]
        col = p.createCollisionShapeArray(types, halfExtents=halves, collisionFramePositions=offsets,
                                          physicsClientId=client)
        vis = -1
        if visual:
            vis = p.createVisualShapeArray(types, halfExtents=halves, visualFramePositions=offsets,
                                           rgbaColors=[list(color)] * len(boxes), physicsClientId=client)
        return col, vis
    kwargs: dict = {}
    if kind == "box":
        assert shape.size_m is not None
        geom = p.GEOM_BOX
        kwargs["halfExtents"] = [s / 2.0 for s in shape.size_m]
    elif kind == "cylinder":
        geom = p.GEOM_CYLINDER
        kwargs["radius"] = shape.radius_m
        col_kwargs = dict(kwargs, height=shape.height_m)
        vis_kwargs = dict(kwargs, length=shape.height_m)  # pybullet's visual cylinder says length
        col = p.createCollisionShape(geom, physicsClientId=client, **col_kwargs)
        vis = p.createVisualShape(geom, rgbaColor=color, physicsClientId=client, **vis_kwargs) if visual else -1
        return col, vis
    elif kind == "sphere":
        geom = p.GEOM_SPHERE
        kwargs["radius"] = shape.radius_m
    else:  # mesh
        geom = p.GEOM_MESH
        kwargs["fileName"] = shape.mesh_file
        kwargs["meshScale"] = list(shape.mesh_scale)
    # static meshes collide as triangle meshes (concave houses); moving ones as convex hulls
    flags = p.GEOM_FORCE_CONCAVE_TRIMESH if kind == "mesh" and static else 0
    col = p.createCollisionShape(geom, flags=flags, physicsClientId=client, **kwargs)
    vis = p.createVisualShape(geom, rgbaColor=color, physicsClientId=client, **kwargs) if visual else -1
    return col, vis


def create_obstacle(client: int, shape: Shape, position_m: Vec3, yaw_rad: float,
                    color: tuple[float, ...], *, mass_kg: float = 0.0, visual: bool = False) -> int:
    """A static (mass 0) or moving (mass > 0, pose driven by a mover) obstacle body."""
    col, vis = _shapes(client, shape, color, visual, static=mass_kg <= 0.0)
    orientation = quaternion_to_pybullet(quat_from_euler_t(0.0, 0.0, yaw_rad))
    body = p.createMultiBody(mass_kg, col, vis, basePosition=list(position_m), baseOrientation=orientation,
                             physicsClientId=client)
    if mass_kg > 0.0:
        # movers set pose and velocity every step; no damping, never sleeps
        p.changeDynamics(body, -1, linearDamping=0.0, angularDamping=0.0,
                         activationState=p.ACTIVATION_STATE_DISABLE_SLEEPING, physicsClientId=client)
    return body


def create_vehicle(client: int, params: IrisParams, position_m: Vec3, yaw_rad: float, *, visual: bool = False) -> int:
    """One rigid body per vehicle: the iris collision box with the iris mass and inertia."""
    half = [s / 2.0 for s in params.collision_box_m]
    col = p.createCollisionShape(p.GEOM_BOX, halfExtents=half, physicsClientId=client)
    vis = _vehicle_visual(client, params, half) if visual else -1
    orientation = quaternion_to_pybullet(yaw_quaternion_enu_flu(yaw_rad))
    body = p.createMultiBody(params.mass_kg, col, vis, basePosition=list(position_m), baseOrientation=orientation,
                             physicsClientId=client)
    # pybullet defaults to 0.04 damping and lets resting bodies sleep: neither is physical here
    p.changeDynamics(body, -1, localInertiaDiagonal=list(params.inertia_kg_m2), linearDamping=0.0,
                     angularDamping=0.0, activationState=p.ACTIVATION_STATE_DISABLE_SLEEPING,
                     physicsClientId=client)
    return body


VEHICLE_RGBA = (1.0, 0.55, 0.0, 1.0)
"""The body: bright orange, visible from afar."""
ROTOR_RGBA = (0.15, 0.15, 0.15, 1.0)
NOSE_RGBA = (0.95, 0.95, 0.95, 1.0)


def _vehicle_visual(client: int, params: IrisParams, half: list[float]) -> int:
    """What a camera sees of a vehicle (collision is the box alone): a flat orange body, a dark
    disc over each rotor, and a white nose on the front (+x, FLU), so heading and attitude show."""
    body_half = [half[0] * 0.45, half[1] * 0.45, half[2]]
    shapes = [p.GEOM_BOX]
    extents: list[dict] = [{"halfExtents": body_half}]
    offsets = [(0.0, 0.0, 0.0)]
    colours = [VEHICLE_RGBA]
    for x, y, _z in params.rotor_positions_flu_m:
        shapes.append(p.GEOM_CYLINDER)
        extents.append({"radius": 0.11, "length": 0.02})
        offsets.append((x, y, half[2]))
        colours.append(ROTOR_RGBA)
    shapes.append(p.GEOM_BOX)
    extents.append({"halfExtents": [0.06, 0.04, half[2] * 0.8]})
    offsets.append((body_half[0] + 0.05, 0.0, 0.0))  # overlaps the body: one piece
    colours.append(NOSE_RGBA)
    return p.createVisualShapeArray(
        shapeTypes=shapes, halfExtents=[e.get("halfExtents", [0.0, 0.0, 0.0]) for e in extents],
        radii=[e.get("radius", 0.0) for e in extents], lengths=[e.get("length", 0.0) for e in extents],
        visualFramePositions=[list(o) for o in offsets], rgbaColors=[list(c) for c in colours],
        physicsClientId=client)

