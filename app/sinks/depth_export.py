"""Depth export (formats.md section 3): ``OUT/<frame stem>.npy`` per frame."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

import numpy as np

from lightflow.app.errors import FrameError, OutputError
from lightflow.app.results import FrameResult, RunStats


def write_atomic(path: Path, write: Callable[[BinaryIO], None]) -> None:
    """Write a file so that readers see it complete or not at all.

    ``write(fh)`` fills a temporary file beside ``path``, which then replaces
    it.  A failure (a full disk) removes the temporary file and becomes one
    :class:`~lightflow.app.errors.OutputError` naming ``path``.
    """
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with open(tmp, "wb") as fh:
            write(fh)
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        why = exc.strerror or str(exc).splitlines()[0]
        raise OutputError(f"{path}: cannot write: {why}") from None


def write_depth_npy(path: Path, depth: np.ndarray) -> None:
    """Write a float32 ``(H, W)`` depth map atomically (readers never see half a file)."""
    if depth.ndim != 2:
        raise FrameError(f"{path}: expected an (H, W) depth map, got shape {depth.shape}")
    data = np.ascontiguousarray(depth, dtype=np.float32)
    write_atomic(path, lambda fh: np.save(fh, data))


class DepthExportSink:
    """Write each frame's depth as ``OUT/<stem>.npy``: float32, metres, NaN without estimate.

    Parameters
    ----------
    out_dir : str or Path
        Created if missing.
    """

    def __init__(self, out_dir: str | Path):
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.written = 0

    def write(self, result: FrameResult, stats: RunStats) -> None:
        write_depth_npy(self.out_dir / f"{result.frame.stem}.npy", result.depth)
        self.written += 1

    def close(self) -> None:
        """Nothing is buffered: every file is complete when ``write`` returns."""

    def describe(self) -> str:
        return f"depth maps: {self.written} files in {self.out_dir}/ (numpy .npy, metres)"
