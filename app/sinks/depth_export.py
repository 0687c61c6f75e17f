"""Depth export (docs/formats.md section 3): ``OUT/<frame stem>.npy`` per frame."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

import numpy as np

from lightflow.app.errors import FrameError, OutputError
from lightflow.app.results import FrameResult, RunStats


def write_complete(path: Path, fill: Callable[[BinaryIO], None]) -> None:
    """Write a file so that ``path`` only ever holds a complete file.

    ``fill(fh)`` writes the content into a temporary file beside ``path``,
    which is renamed over ``path`` when complete.  On any failure (a full disk,
    a file size limit) the temporary file is removed and an :class:`OutputError`
    names the file.

    Parameters
    ----------
    path : Path
        The final file.
    fill : callable
        Writes the content to the binary file object it is given.
    """
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with open(tmp, "wb") as fh:
            fill(fh)
        os.replace(tmp, path)
    except OSError as exc:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:  # noqa: S110 - the write error is the one to report
            pass
        # a short write ("N requested and M written") carries no errno: the disk
        # filled up or a file size limit was reached
        reason = exc.strerror or f"disk full or file size limit ({str(exc).splitlines()[0]})"
        raise OutputError(f"{path}: cannot write: {reason}") from None


def make_output_dir(path: str | Path) -> Path:
    """Create an output folder, turning I/O errors into one :class:`OutputError` line."""
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
    write_complete(path, lambda fh: np.save(fh, data))


class DepthExportSink:
    """Write each frame's depth as ``OUT/<stem>.npy``: float32, metres, NaN without estimate.

    Parameters
    ----------
    out_dir : str or Path
        Created if missing.
    """

    def __init__(self, out_dir: str | Path):
        self.out_dir = make_output_dir(out_dir)
        self.written = 0

    def write(self, result: FrameResult, stats: RunStats) -> None:
        write_depth_npy(self.out_dir / f"{result.frame.stem}.npy", result.depth)
        self.written += 1

    def close(self) -> None:
        """Nothing is buffered: every file is complete when ``write`` returns."""

    def describe(self) -> str:
        return f"depth maps: {self.written} files in {self.out_dir}/ (numpy .npy, metres)"
