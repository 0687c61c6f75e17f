"""Depth export (formats.md section 3): ``OUT/<frame stem>.npy`` per frame."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from lightflow.app.errors import FrameError
from lightflow.app.results import FrameResult, RunStats


def write_depth_npy(path: Path, depth: np.ndarray) -> None:
    """Write a float32 ``(H, W)`` depth map atomically (readers never see half a file)."""
    if depth.ndim != 2:
        raise FrameError(f"{path}: expected an (H, W) depth map, got shape {depth.shape}")
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as fh:
        np.save(fh, np.ascontiguousarray(depth, dtype=np.float32))
    os.replace(tmp, path)


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
