"""Point-cloud export: one binary little-endian PLY per frame, coloured from the camera."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from lightflow.app.errors import FrameError
from lightflow.app.geometry import camera_rays
from lightflow.app.results import FrameResult, RunStats
from lightflow.app.rig import Rig

PLY_DTYPE = np.dtype(
    [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
)


def image_to_rgb8(image: np.ndarray) -> np.ndarray:
    """An RGB uint8 view of a uint8 or uint16 camera image (16-bit keeps its top byte)."""
    if image.dtype == np.uint16:
        return (image >> 8).astype(np.uint8)
    return image.astype(np.uint8, copy=False)


def depth_to_points(
    depth: np.ndarray,
    rays: np.ndarray,
    image: np.ndarray | None = None,
    max_points: int | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Camera-frame points ``(n, 3)`` float32 for the pixels with a depth, and their colours.

    Parameters
    ----------
    depth : numpy.ndarray
        ``(H, W)`` depth z in metres, NaN without estimate.
    rays : numpy.ndarray
        ``(H, W, 3)`` rays with z = 1 (:func:`lightflow.app.geometry.camera_rays`).
    image : numpy.ndarray, optional
        ``(H, W, 3)`` RGB image giving the colours (uint8 ``(n, 3)``).
    max_points : int, optional
        Keep at most this many points, evenly spread over the valid pixels in
        row-major order (chosen before any arithmetic, so subsampling is cheap).
    """
    idx = np.flatnonzero(np.isfinite(depth))
    if max_points is not None and len(idx) > max_points:
        idx = idx[np.linspace(0, len(idx) - 1, max_points).astype(np.intp)]
    z = depth.reshape(-1).take(idx).astype(np.float32)
    points = rays.reshape(-1, 3).take(idx, axis=0).astype(np.float32, copy=False)
    points *= z[:, None]
    colors = None
    if image is not None:
        colors = image_to_rgb8(image.reshape(-1, 3).take(idx, axis=0))
    return points, colors


def write_ply(path: Path, points: np.ndarray, colors: np.ndarray) -> None:
    """Write a binary little-endian PLY with x y z (float32) and red green blue (uint8)."""
    vertices = np.empty(len(points), dtype=PLY_DTYPE)
    vertices["x"], vertices["y"], vertices["z"] = points.T
    vertices["red"], vertices["green"], vertices["blue"] = colors.T
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment lightflow depth, camera frame, metres\n"
        f"element vertex {len(vertices)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(vertices.tobytes())
    os.replace(tmp, path)


class PlyExportSink:
    """Write ``OUT/<stem>.ply`` per frame: coloured points in the camera frame (metres).

    Parameters
    ----------
    out_dir : str or Path
        Created if missing.
    rig : Rig
        Its camera model turns depth into points (lens distortion included).
    """

    def __init__(self, out_dir: str | Path, rig: Rig):
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.camera = rig.camera
        self._rays = camera_rays(rig.camera).astype(np.float32)  # once: undistortion is slow
        self.written = 0

    def write(self, result: FrameResult, stats: RunStats) -> None:
        path = self.out_dir / f"{result.frame.stem}.ply"
        cam = self.camera
        if result.depth.shape != (cam.height, cam.width):
            h, w = result.depth.shape[:2]
            raise FrameError(
                f"{path}: depth is {w}x{h}, the rig camera is {cam.width}x{cam.height}"
            )
        points, colors = depth_to_points(result.depth, self._rays, result.frame.image)
        write_ply(path, points, colors)
        self.written += 1

    def close(self) -> None:
        """Nothing is buffered: every file is complete when ``write`` returns."""

    def describe(self) -> str:
        return f"point clouds: {self.written} PLY files in {self.out_dir}/"
