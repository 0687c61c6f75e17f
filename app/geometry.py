"""Camera and projector geometry with the full OpenCV lens model (pure numpy/OpenCV)."""

from __future__ import annotations

import cv2
import numpy as np

from .rig import CameraModel, ProjectorModel

_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


def undistort_pixels(K: np.ndarray, dist: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Map pixel coordinates to undistorted normalised coordinates.

    Parameters
    ----------
    K, dist : numpy.ndarray
        OpenCV intrinsics and distortion coefficients.
    pixels : numpy.ndarray
        ``(..., 2)`` pixel coordinates.

    Returns
    -------
    numpy.ndarray
        ``(..., 2)`` normalised coordinates ``(x/z, y/z)`` of the rays.
    """
    shape = pixels.shape
    pts = np.ascontiguousarray(pixels.reshape(-1, 1, 2), dtype=np.float64)
    if not np.any(dist):
        out = (pts[:, 0, :] - K[:2, 2]) @ np.linalg.inv(K[:2, :2]).T
        return out.reshape(shape)
    und = cv2.undistortPointsIter(pts, K, dist, None, None, _UNDISTORT_CRITERIA)
    return und.reshape(shape)


def grid_shape(width: int, height: int, stride: int) -> tuple[int, int]:
    """``(rows, cols)`` of the analysis grid: one sample per ``stride`` x ``stride`` cell."""
    return height // stride, width // stride


def pixel_grid(width: int, height: int, stride: int = 1) -> np.ndarray:
    """Centres ``(h, w, 2)`` of the ``stride`` x ``stride`` cells of the image.

    Cell (i, j) covers pixels ``[i s, i s + s)``; its centre is ``i s + (s - 1) / 2``,
    which is exactly where ``cv2.resize`` puts grid samples when upsampling.
    """
    gh, gw = grid_shape(width, height, stride)
    off = (stride - 1) / 2
    xs = np.arange(gw, dtype=np.float64) * stride + off
    ys = np.arange(gh, dtype=np.float64) * stride + off
    gx, gy = np.meshgrid(xs, ys)
    return np.stack([gx, gy], axis=-1)


def camera_rays(camera: CameraModel, stride: int = 1) -> np.ndarray:
    """Rays ``(h, w, 3)`` with z = 1 through the camera's pixel centres (distortion removed)."""
    xy = undistort_pixels(camera.K, camera.dist, pixel_grid(camera.width, camera.height, stride))
    return np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)


def distort_normalized(x: np.ndarray, y: np.ndarray, dist: np.ndarray):
    """Apply the OpenCV distortion model to normalised coordinates.

    Supports k1, k2, p1, p2, k3, the rational k4..k6 and the thin prism s1..s4.
    (The tilted-sensor terms of the 14-coefficient model are not applied.)
    """
    d = np.zeros(12)
    d[: min(len(dist), 12)] = dist[:12]
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = d
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r2 * r2
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r2 * r2
    return xd, yd


def project_points(K: np.ndarray, dist: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Project ``(..., 3)`` points given in the device's own frame to pixels ``(..., 2)``."""
    z = points[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = points[..., 0] / z
        y = points[..., 1] / z
    xd, yd = distort_normalized(x, y, dist)
    u = K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
    v = K[1, 1] * yd + K[1, 2]
    return np.stack([u, v], axis=-1)


def to_projector(projector: ProjectorModel, points_cam: np.ndarray) -> np.ndarray:
    """Transform ``(..., 3)`` camera-frame points into the projector frame."""
    return points_cam @ projector.R.T + projector.t


def project_to_projector(projector: ProjectorModel, points_cam: np.ndarray) -> np.ndarray:
    """Projector pixel ``(u, v)`` that lights each camera-frame point."""
    return project_points(projector.K, projector.dist, to_projector(projector, points_cam))
