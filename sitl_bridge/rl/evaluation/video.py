"""Videos of what a policy did: the env's `rgb_array` frames of each episode, one MP4 per
episode (imageio with its ffmpeg plugin: the `video` extra)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


class VideoUnavailable(RuntimeError):
    """The `video` extra (imageio, imageio-ffmpeg) is not installed."""


def require_video_support() -> None:
    """Fail early, with how to fix it, when videos cannot be written."""
    try:
        import imageio.v3  # noqa: F401
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        raise VideoUnavailable("recording videos needs the `video` extra: pip install -e \".[video]\"") from None


class EpisodeVideos:
    """Collects frames per episode and writes `path_for(episode)` when the episode ends."""

    def __init__(self, path_for, fps: int, *, single: bool = False) -> None:  # noqa: ANN001 - (int) -> Path
        require_video_support()
        self.path_for = path_for
        self.fps = fps
        self.single = single
        """All episodes into one file, written by `close()`."""
        self.frames: list[np.ndarray] = []
        self.written: list[Path] = []

    @classmethod
    def into_file(cls, path: str | Path, fps: int) -> EpisodeVideos:
        """Every episode into one file (`run --policy --video FILE.mp4`: later episodes are
        appended to the same video)."""
        return cls(lambda _episode: Path(path), fps, single=True)

    @classmethod
    def into_folder(cls, folder: str | Path, fps: int) -> EpisodeVideos:
        """One `episode_NNNN.mp4` per episode in `folder` (`eval --video DIR`)."""
        Path(folder).mkdir(parents=True, exist_ok=True)
        return cls(lambda episode: Path(folder) / f"episode_{episode:04d}.mp4", fps)

    def add(self, frame: np.ndarray | list[np.ndarray] | None) -> None:
        """One frame, or the list of an `rgb_array_list` env (None is ignored: an env without
        rgb_array rendering)."""
        if isinstance(frame, list):
            self.frames.extend(np.asarray(f, dtype=np.uint8) for f in frame)
        elif frame is not None:
            self.frames.append(np.asarray(frame, dtype=np.uint8))

    def end_episode(self, episode: int) -> None:
        """Write the episode's frames (or, for a single file, keep them for `close`)."""
        if not self.single:
            self._write(self.path_for(episode))

    def close(self) -> None:
        """Write what is left (the single file)."""
        if self.single and self.frames:
            self._write(self.path_for(0))

    def _write(self, path: Path) -> None:
        import imageio.v3 as iio

        if self.frames:
            path.parent.mkdir(parents=True, exist_ok=True)
            iio.imwrite(path, np.stack(self.frames), plugin="FFMPEG", fps=self.fps)
            self.written.append(path)
        self.frames = []
