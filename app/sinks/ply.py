"""Point-cloud export (docs/formats.md section 5): one binary PLY per frame.

Points are in the *world frame* of the PLY files: the camera frame turned
half a turn about its x axis, so x points right, y up and the scene lies at
negative z (the OpenGL convention most point-cloud viewers start in).  They are
coloured by depth (a turbo colour scale, near = blue, far = red, over the
frame's 2nd..98th percentile of depth) so that every point is visible however
dark the camera image is; ``colors="image"`` takes the camera colours instead,
stretched so the brightest of them is white.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from lightflow.app.errors import ConfigError, FrameError
from lightflow.app.geometry import camera_rays
from lightflow.app.results import FrameResult, RunStats
from lightflow.app.rig import Rig
from lightflow.app.sinks.depth_export import make_output_dir, write_complete

#: camera axes (x right, y down, z forward) to PLY world axes (x right, y up, z back)
CAMERA_TO_WORLD = np.diag([1.0, -1.0, -1.0]).astype(np.float32)
COLOR_MODES = ("depth", "image")

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


def depth_colors(z: np.ndarray) -> np.ndarray:
    """Turbo colours ``(n, 3)`` uint8 for depths ``z``, near blue to far red.

    The scale spans the 2nd..98th percentile of ``z`` so one stray point does
    not wash out the rest.
    """
    if len(z) == 0:
        return np.zeros((0, 3), np.uint8)
    lo, hi = np.percentile(z, [2, 98])
    scaled = np.clip((z - lo) / max(hi - lo, 1e-6), 0, 1)
    idx = (scaled * 255).astype(np.uint8).reshape(-1, 1)
    bgr = cv2.applyColorMap(idx, cv2.COLORMAP_TURBO).reshape(-1, 3)
    return np.ascontiguousarray(bgr[:, ::-1])


def normalised_colors(colors: np.ndarray) -> np.ndarray:
    """Camera colours ``(n, 3)`` (any dtype) stretched so their 99th percentile is white."""
    if len(colors) == 0:
        return np.zeros((0, 3), np.uint8)
    values = colors.astype(np.float32)
    top = float(np.percentile(values.max(axis=1), 99))
    return np.clip(values * (255.0 / max(top, 1.0)), 0, 255).astype(np.uint8)


def write_ply(path: Path, points: np.ndarray, colors: np.ndarray,
              comment: str = "lightflow depth, camera frame, metres") -> None:  # fmt: skip
    """Write a binary little-endian PLY with x y z (float32) and red green blue (uint8).

    The file appears complete or not at all; a full disk raises :class:`OutputError`.
    """
    vertices = np.empty(len(points), dtype=PLY_DTYPE)
    vertices["x"], vertices["y"], vertices["z"] = points.T
    vertices["red"], vertices["green"], vertices["blue"] = colors.T
    header = (
        f"ply\nformat binary_little_endian 1.0\ncomment {comment}\n"
        f"element vertex {len(vertices)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )

    def fill(fh) -> None:
        fh.write(header.encode("ascii"))
        fh.write(vertices.tobytes())

    write_complete(path, fill)


class PlyExportSink:
    """Write ``OUT/<stem>.ply`` per frame: coloured points in world axes (y up, metres).

    Parameters
    ----------
    out_dir : str or Path
        Created if missing.
    rig : Rig
        Its camera model turns depth into points (lens distortion included).
    colors : str
        ``depth`` (default: a colour scale over depth) or ``image`` (the
        camera's colours, stretched to full brightness).
    """

    def __init__(self, out_dir: str | Path, rig: Rig, colors: str = "depth"):
        if colors not in COLOR_MODES:
            raise ConfigError(f"colors: expected one of {', '.join(COLOR_MODES)}, got {colors!r}")
        self.colors = colors
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
        points, colors = depth_to_points(result.depth, self._rays, result.frame.image)
        if self.colors == "depth":
            colors = depth_colors(points[:, 2])
        else:
            image = result.frame.image.reshape(-1, 3)
            colors = normalised_colors(image.take(np.flatnonzero(np.isfinite(result.depth)),
                                                  axis=0))  # fmt: skip
        write_ply(path, points @ CAMERA_TO_WORLD, colors,
                  comment="lightflow depth, world frame x right y up z back, metres")
        self.written += 1

    def close(self) -> None:
        """Nothing is buffered: every file is complete when ``write`` returns."""

    def describe(self) -> str:
        return f"point clouds: {self.written} PLY files in {self.out_dir}/"
