"""Point-cloud export: one binary little-endian PLY per frame, coloured by depth."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from lightflow.app.core.errors import FrameError
from lightflow.app.core.geometry import camera_rays
from lightflow.app.core.results import FrameResult, RunStats
from lightflow.app.core.rig import Rig
from lightflow.app.sinks.depth_export import make_output_dir, write_atomic

PLY_DTYPE = np.dtype(
    [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
)


def image_to_rgb8(image: np.ndarray, full_scale: float | None = None) -> np.ndarray:
    """An RGB uint8 copy of a camera image.

    ``full_scale`` is the sample value of full exposure (4095 for a 12-bit
    camera, see :attr:`Frame.full_scale`); by default the dtype's maximum.
    """
    if full_scale is None:
        full_scale = 65535.0 if image.dtype == np.uint16 else 255.0
    if full_scale == 255.0 and image.dtype == np.uint8:
        return image.copy()
    return np.clip(image * (255.0 / full_scale), 0, 255).astype(np.uint8)


def depth_colors(z: np.ndarray) -> np.ndarray:
    """Turbo colours (uint8 ``(n, 3)`` RGB) over the 2-98 % range of depths ``z``."""
    if len(z) == 0:
        return np.zeros((0, 3), np.uint8)
    lo, hi = np.percentile(z, [2, 98])
    t = np.clip((z - lo) / max(hi - lo, 1e-6), 0, 1)
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_TURBO)
    # the ends of turbo are nearly black: use its bright middle, 10-90 %
    return lut[(25.5 + t * 204).astype(np.intp), 0, ::-1].copy()  # BGR -> RGB


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
        ``(H, W, 3)`` rays with z = 1 (:func:`lightflow.app.core.geometry.camera_rays`).
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
    """Write a binary little-endian PLY with x y z (float32) and red green blue (uint8).

    Points are in the PLY frame of the format document: metres, right-handed,
    x right, y up, z from the scene towards the camera, camera at the origin.
    """
    vertices = np.empty(len(points), dtype=PLY_DTYPE)
    vertices["x"], vertices["y"], vertices["z"] = points.T
    vertices["red"], vertices["green"], vertices["blue"] = colors.T
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        "comment lightflow depth, metres, x right, y up, z towards the camera\n"
        f"element vertex {len(vertices)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )

    def write(fh) -> None:
        fh.write(header.encode("ascii"))
        fh.write(vertices.tobytes())

    write_atomic(path, write)


class PlyExportSink:
    """Write ``OUT/<stem>.ply`` per frame: points coloured by depth (metres, y up).

    Parameters
    ----------
    out_dir : str or Path
        Created if missing.
    rig : Rig
        Its camera model turns depth into points (lens distortion included).
    """

    def __init__(self, out_dir: str | Path, rig: Rig):
        self.out_dir = make_output_dir(out_dir)
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
        points, _ = depth_to_points(result.depth, self._rays)
        colors = depth_colors(points[:, 2])  # camera images are mostly dark: colour by depth
        points[:, 1:] *= -1  # camera axes (y down, z forward) -> y up, z towards the camera
        write_ply(path, points, colors)
        self.written += 1

    def close(self) -> None:
        """Nothing is buffered: every file is complete when ``write`` returns."""

    def describe(self) -> str:
        return f"point clouds: {self.written} PLY files in {self.out_dir}/"
