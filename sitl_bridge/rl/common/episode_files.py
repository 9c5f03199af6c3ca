"""Episode logs on disk, plain or compressed: `episodes.jsonl`, or `episodes.jsonl.xz` in a slimmed run.

A finished run's episode log is read, never appended to again, and compresses about 8:1 with
xz (stdlib `lzma`); every reader opens it through `open_log`, so either form reads the same.
"""

from __future__ import annotations

import errno
import lzma
import os
from pathlib import Path
from typing import BinaryIO

from sitl_bridge.rl.common.atomic import fsync_dir

COMPRESSED_SUFFIX = ".xz"


def compressed_path(path: str | Path) -> Path:
    path = Path(path)
    return path.with_name(path.name + COMPRESSED_SUFFIX)


def log_exists(path: str | Path) -> bool:
    """Whether the log at `path` exists, plain or compressed."""
    return Path(path).is_file() or compressed_path(path).is_file()


def open_log(path: str | Path) -> BinaryIO:
    """The log at `path` for reading (bytes), decompressing `path.xz` when only that exists;
    FileNotFoundError naming both when neither does."""
    path = Path(path)
    if path.is_file():
        return open(path, "rb")
    if compressed_path(path).is_file():
        return lzma.open(compressed_path(path), "rb")  # type: ignore[return-value]
    raise FileNotFoundError(errno.ENOENT, f"No such file or directory (nor {compressed_path(path).name})", str(path))


def compress_log(path: str | Path) -> tuple[int, int]:
    """Replace the log at `path` by `path.xz`, removing the plain file only after the written
    archive decompresses to exactly its bytes. Returns (bytes before, bytes after)."""
    path = Path(path)
    original = path.read_bytes()
    target = compressed_path(path)
    temporary = target.with_name(f".{target.name}.tmp{os.getpid()}")
    try:
        with open(temporary, "wb") as handle:
            handle.write(lzma.compress(original, preset=9 | lzma.PRESET_EXTREME))
            handle.flush()
            os.fsync(handle.fileno())
        with lzma.open(temporary, "rb") as check:
            if check.read() != original:
                raise OSError(f"{temporary}: the compressed log does not read back as {path.name}")
        os.replace(temporary, target)
    finally:
        temporary.unlink(missing_ok=True)
    fsync_dir(target.parent)
    path.unlink()
    fsync_dir(path.parent)
    return len(original), target.stat().st_size
