"""Pictures of a running simulation: an offscreen camera (pybullet's TinyRenderer, no display
needed) and marker bodies for what the physics does not hold (goal regions, the workspace).

Markers are visual-only multibodies (no collision shape), so lidar rays and contacts never see
them; they exist only while a `SceneCamera` is attached, so a simulation that is never
rendered carries nothing extra. A simulation is built with `visual=True` for its bodies to have
colours (see `Simulation`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pybullet as p

from sitl_bridge.frames import quat_to_euler
from sitl_bridge.physics.simulation import Simulation

CAMERA_MODES = ("scene", "follow")
GOAL_RGBA = (0.1, 0.85, 0.2, 1.0)
GOAL_EDGE_M = 0.08
WORKSPACE_RGBA = (0.15, 0.35, 0.9, 1.0)
WORKSPACE_EDGE_M = 0.04
RAY_RGB = (255, 200, 0)


FOLLOW_DISTANCE_M = 4.0
"""Default follow-camera distance: a 0.5 m drone is ~50 px wide in a 512-px, 60-degree frame."""


@dataclass(frozen=True)
class RenderConfig:
    """Camera of a scenario (`task.render:` in its YAML; every key optional)."""

    width: int = 512
    height: int = 384
    """Pixels; multiples of 16 keep video encoders from resizing."""
    camera: str = "follow"
    """`follow` (default): behind and above the drone, looking along its heading, so the drone
    is tens of pixels wide; `scene`: frames the whole workspace (the drone a few pixels)."""
    distance_m: float | None = None
    """Camera distance from its target (default: fits the workspace / `FOLLOW_DISTANCE_M` when following)."""
    yaw_deg: float = 30.0
    """Scene camera's yaw about the vertical (pybullet convention: 0 looks along +y); the follow
    camera takes the drone's heading instead."""
    pitch_deg: float = -35.0
    """Negative looks down."""
    target_m: tuple[float, float, float] | None = None
    """Point the scene camera looks at (default: the workspace centre)."""
    fov_deg: float = 60.0
    lidar_rays: bool = False
    """Draw the lidar rays of the followed drone (or of every drone in scene mode)."""
    fps: int = 10
    """Frames per second of recorded videos: with frames every 0.1 s of simulated time
    (`render_mode="rgb_array_list"`), 10 plays the flight at its own pace."""


class SceneCamera:
    """Renders RGB frames of `sim` (H x W x 3, uint8) with goal and workspace markers."""

    def __init__(self, sim: Simulation, config: RenderConfig | None = None) -> None:
        self.sim = sim
        self.config = config or RenderConfig()
        self._built_for = -1
        self._goal_markers: list[list[tuple[int, np.ndarray]]] = []  # per goal: (edge body, offset)

    # -- frames ---------------------------------------------------------------------------
    def frame(self, follow: int | None = None,
              rays: Sequence[tuple[np.ndarray, np.ndarray]] = ()) -> np.ndarray:
        """One picture; `follow` = vehicle to follow in `follow` mode (default 0); `rays` =
        (start, end) world points of lidar rays to draw."""
        self._ensure_markers()
        config = self.config
        view = self._view_matrix(follow)
        projection = p.computeProjectionMatrixFOV(config.fov_deg, config.width / config.height, 0.05, 200.0)
        _, _, rgba, _, _ = p.getCameraImage(config.width, config.height, viewMatrix=view,
                                            projectionMatrix=projection, renderer=p.ER_TINY_RENDERER,
                                            shadow=0, lightDirection=(0.4, -0.6, 1.0),
                                            physicsClientId=self.sim.client_id)
        image = np.asarray(rgba, dtype=np.uint8).reshape(config.height, config.width, 4)[:, :, :3].copy()
        if rays:
            _draw_segments(image, rays, np.asarray(view).reshape(4, 4).T,
                           np.asarray(projection).reshape(4, 4).T, RAY_RGB)
        return image

    def _view_matrix(self, follow: int | None) -> Sequence[float]:
        config = self.config
        low = np.asarray(self.sim.world.workspace.min_m, dtype=float)
        high = np.asarray(self.sim.world.workspace.max_m, dtype=float)
        if config.camera == "follow":
            state = self.sim.state(follow or 0)
            target = state.position_enu_m
            distance = config.distance_m or FOLLOW_DISTANCE_M
            # behind the drone: pybullet's camera at yaw 0 looks along +y (ENU north, heading 90 deg)
            heading_deg = math.degrees(quat_to_euler(state.quaternion_enu_flu)[2])
            return p.computeViewMatrixFromYawPitchRoll([float(v) for v in target], distance, heading_deg - 90.0,
                                                      config.pitch_deg, 0.0, 2)
        else:
            target = np.asarray(config.target_m if config.target_m is not None else (low + high) / 2.0)
            span = float(np.linalg.norm(high - low))
            distance = config.distance_m or max(4.0, 0.9 * span / math.tan(math.radians(config.fov_deg) / 2.0) / 2.0)
        return p.computeViewMatrixFromYawPitchRoll([float(v) for v in target], distance, config.yaw_deg,
                                                  config.pitch_deg, 0.0, 2)

    # -- markers --------------------------------------------------------------------------
    def _ensure_markers(self) -> None:
        """(Re)create the markers after a rebuild of the world, move goals to this episode's.
        Goal regions and the workspace are drawn as box edges (TinyRenderer has no
        transparency: a solid goal box would hide the drone inside it)."""
        cid = self.sim.client_id
        if self._built_for != self.sim.build_count:
            self._goal_markers = [_box_edges(cid, goal.center_m, goal.size_m, GOAL_RGBA, GOAL_EDGE_M)
                                  for goal in self.sim.layout.goals]
            low = np.asarray(self.sim.world.workspace.min_m, dtype=float)
            high = np.asarray(self.sim.world.workspace.max_m, dtype=float)
            _box_edges(cid, (low + high) / 2.0, high - low, WORKSPACE_RGBA, WORKSPACE_EDGE_M)
            self._built_for = self.sim.build_count
        for edges, goal in zip(self._goal_markers, self.sim.layout.goals, strict=True):
            centre = np.asarray(goal.center_m, dtype=float)
            for body, offset in edges:
                p.resetBasePositionAndOrientation(body, (centre + offset).tolist(), (0.0, 0.0, 0.0, 1.0),
                                                  physicsClientId=cid)


def _visual_box(client: int, size_m: Sequence[float], centre_m: Sequence[float],
                rgba: Sequence[float]) -> int:
    shape = p.createVisualShape(p.GEOM_BOX, halfExtents=[s / 2.0 for s in size_m], rgbaColor=rgba,
                                physicsClientId=client)
    return p.createMultiBody(baseMass=0.0, baseCollisionShapeIndex=-1, baseVisualShapeIndex=shape,
                             basePosition=list(centre_m), physicsClientId=client)


def _box_edges(client: int, centre: Sequence[float], size: Sequence[float], rgba: Sequence[float],
               thickness_m: float) -> list[tuple[int, np.ndarray]]:
    """The 12 edges of a box as thin visual bars: (body, offset from the centre) each."""
    half = np.asarray(size, dtype=float) / 2.0
    centre = np.asarray(centre, dtype=float)
    edges = []
    for axis in range(3):
        others = [a for a in range(3) if a != axis]
        for signs in ((-1, -1), (-1, 1), (1, -1), (1, 1)):
            offset = np.zeros(3)
            extent = np.full(3, thickness_m)
            extent[axis] = 2.0 * half[axis]
            for other, sign in zip(others, signs, strict=True):
                offset[other] = sign * half[other]
            edges.append((_visual_box(client, extent, centre + offset, rgba), offset))
    return edges


def _draw_segments(image: np.ndarray, segments: Sequence[tuple[np.ndarray, np.ndarray]],
                   view: np.ndarray, projection: np.ndarray, rgb: tuple[int, int, int]) -> None:
    """Paint world-space segments onto `image` (OpenGL matrices, column-major from pybullet)."""
    height, width = image.shape[:2]
    clip_from_world = projection @ view
    for start, end in segments:
        points = np.linspace(np.asarray(start, dtype=float), np.asarray(end, dtype=float), 64)
        clip = clip_from_world @ np.vstack([points.T, np.ones(len(points))])
        visible = clip[3] > 1e-6
        ndc = clip[:3, visible] / clip[3, visible]
        cols = np.round((ndc[0] + 1.0) / 2.0 * (width - 1)).astype(int)
        rows = np.round((1.0 - ndc[1]) / 2.0 * (height - 1)).astype(int)
        inside = (cols >= 0) & (cols < width) & (rows >= 0) & (rows < height)
        image[rows[inside], cols[inside]] = rgb
