"""Depth export (formats.md section 3): ``OUT/<frame stem>.npy`` per frame."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

import numpy as np

from lightflow.app.core.errors import FrameError, OutputError
from lightflow.app.core.results import FrameResult, RunStats


def write_atomic(path: Path, write: Callable[[BinaryIO], None]) -> None:
    """Write a file so that readers see it complete or not at all.

    ``write(fh)`` fills a temporary file beside ``path``, which then replaces
    it.  A failure (a full disk) removes the temporary file and becomes one
    :class:`~lightflow.app.core.errors.OutputError` naming ``path``.
    """
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with open(tmp, "wb") as fh:
            write(fh)
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        # a short write ("N requested and M written") carries no errno: the disk
        # filled up or a file size limit was reached
        why = exc.strerror or f"disk full or file size limit ({str(exc).splitlines()[0]})"
        raise OutputError(f"{path}: cannot write: {why}") from None


def make_output_dir(path: str | Path) -> Path:
    """Create an output folder; an I/O error becomes one :class:`OutputError` line."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{path}: cannot create the output folder: {exc.strerror}") from None
    return path


def write_depth_npy(path: Path, depth: np.ndarray) -> None:
    """Write a float32 ``(H, W)`` depth map atomically (readers never see half a file)."""
    if depth.ndim != 2:
        raise FrameError(f"{path}: expected an (H, W) depth map, got shape {depth.shape}")
    data = np.ascontiguousarray(depth, dtype=np.float32)
    write_atomic(path, lambda fh: np.save(fh, data))


class DepthExportSink:
    """Write each frame's depth as ``OUT/<stem>.npy``: float32, metres, NaN without estimate.

    Beside it, ``OUT/<stem>_std.npy``: the predicted standard deviation of each
    depth (float32, metres, NaN where there is no depth).

    Parameters
    ----------
    out_dir : str or Path
        Created if missing.
    """

    def __init__(self, out_dir: str | Path):
        self.out_dir = make_output_dir(out_dir)
        self.written = 0

    def write(self, result: FrameResult, stats: RunStats) -> None:
        stem = result.frame.stem
        if result.depth_std is not None:
            write_depth_npy(self.out_dir / f"{stem}_std.npy", result.depth_std)
        # the depth last: a complete depth file means its std file is complete too
        write_depth_npy(self.out_dir / f"{stem}.npy", result.depth)
        self.written += 1

    def close(self) -> None:
        """Nothing is buffered: every file is complete when ``write`` returns."""

    def describe(self) -> str:
        return (f"depth maps: {self.written} frames in {self.out_dir}/ (numpy .npy, metres; "
                f"<frame>_std.npy: predicted standard deviation)")  # fmt: skip
