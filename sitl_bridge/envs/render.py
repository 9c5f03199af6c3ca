"""Rendering of the envs: `render_mode="rgb_array"` frames from an offscreen camera on the
backend's simulation (`physics.render.SceneCamera`), and the camera of `render_mode="human"`
(pybullet's GUI) following the drone. Nothing here runs unless a render mode is set."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pybullet as p

from sitl_bridge.envs.backends.base import Backend, Snapshot
from sitl_bridge.frames import quat_rotate
from sitl_bridge.physics.render import RenderConfig, SceneCamera
from sitl_bridge.physics.simulation import Simulation
from sitl_bridge.sensors.lidar import ray_directions_flu
from sitl_bridge.world import World


class EnvRenderer:
    """Frames of one env's backend (the camera follows its simulation across restarts)."""

    def __init__(self, world: World, config: RenderConfig, backend: Backend, mode: str | None) -> None:
        self.world = world
        self.config = config
        self.backend = backend
        self.mode = mode
        self._camera: SceneCamera | None = None

    def render(self, follow: int | None, snapshot: Snapshot | None) -> np.ndarray | None:
        """The frame for `render()`: an RGB array (`rgb_array`), or None after pointing the GUI
        camera at the drone (`human`)."""
        if self.mode in ("rgb_array", "rgb_array_list"):
            return self.backend.with_simulation(lambda sim: self._frame(sim, follow, snapshot))
        if self.mode == "human":
            self.backend.with_simulation(lambda sim: self._point_gui(sim, follow))
        return None

    def _frame(self, sim: Simulation, follow: int | None, snapshot: Snapshot | None) -> np.ndarray:
        if self._camera is None or self._camera.sim is not sim:
            self._camera = SceneCamera(sim, self.config)
        rays = self._rays(follow, snapshot) if self.config.lidar_rays and snapshot is not None else []
        return self._camera.frame(follow, rays)

    def _rays(self, follow: int | None, snapshot: Snapshot) -> list[tuple[np.ndarray, np.ndarray]]:
        """World-space segments of the lidar rays as last scanned (followed drone, or all)."""
        drones = [follow] if follow is not None else range(len(snapshot.states))
        segments = []
        for i in drones:
            state, scan = snapshot.states[i], snapshot.scans[i]
            origin = np.asarray(state.position_enu_m, dtype=float)
            directions = np.vstack(ray_directions_flu(self.world.vehicles[i].lidar))
            ranges = np.concatenate([scan.horizontal_m, scan.up_m, scan.down_m])
            for direction, distance in zip(directions, ranges, strict=True):
                end = origin + quat_rotate(state.quaternion_enu_flu, direction) * float(distance)
                segments.append((origin, end))
        return segments

    def _point_gui(self, sim: Simulation, follow: int | None) -> None:
        target = sim.state(follow or 0).position_enu_m
        p.resetDebugVisualizerCamera(self.config.distance_m or 6.0, self.config.yaw_deg, self.config.pitch_deg,
                                     [float(v) for v in target], physicsClientId=sim.client_id)


class FrameList:
    """`render_mode="rgb_array_list"`: the frames since the last `render()`, one after the
    reset and one every `watched_flight.FRAME_PERIOD_S` of simulated time through each action
    (the runner calls `capture` while it flies), so a video plays the flight at its own pace."""

    def __init__(self, renderer: EnvRenderer, follow: Callable[[], int | None],
                 snapshot: Callable[[], Snapshot | None]) -> None:
        self.renderer = renderer
        self.follow = follow
        self.snapshot = snapshot
        self.frames: list[np.ndarray] = []

    def capture(self) -> None:
        frame = self.renderer.render(self.follow(), self.snapshot())
        if frame is not None:
            self.frames.append(frame)

    def restart(self) -> None:
        """A new episode: drop what the last one left, keep its first frame."""
        self.frames = []
        self.capture()

    def take(self) -> list[np.ndarray]:
        frames, self.frames = self.frames, []
        return frames

