"""Camera and projector geometry with the full OpenCV lens model (numpy, OpenCV, numba).

The core's lens model is written once, here: :func:`lens_distort` and its
derivative :func:`lens_distort_derivative` are scalar numba functions on the
12 coefficients of :func:`lens_coefficients`.  The numpy functions below call
the same source on arrays (``.py_func``), and the depth model's kernels call it
compiled, so the depth table and the numpy projection cannot drift apart.  The
simulator does not use it: it projects with OpenCV itself, and a test checks
that the two agree.
"""

from __future__ import annotations

import cv2
import numba as nb
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
    if K[0, 1] != 0:
        # OpenCV's lens model has no skew (undistortPoints and projectPoints ignore
        # K[0, 1]); take it out of the columns first, as project_points puts it in
        pts = pts.copy()
        pts[:, 0, 0] -= K[0, 1] * (pts[:, 0, 1] - K[1, 2]) / K[1, 1]
        K = np.array(K, np.float64)
        K[0, 1] = 0.0
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


#: coefficients of the lens model: k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4
LENS_COEFFICIENTS = 12


def lens_coefficients(dist) -> np.ndarray:
    """The ``(12,)`` float64 coefficients of :func:`lens_distort` from OpenCV's ``dist``.

    Parameters
    ----------
    dist : array_like
        OpenCV distortion coefficients (4, 5, 8, 12 or 14 of them; missing ones are 0).

    Returns
    -------
    numpy.ndarray
        k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4.  The tilted-sensor
        terms ``tau_x, tau_y`` of the 14-coefficient model are not applied.
    """
    d = np.zeros(LENS_COEFFICIENTS)
    src = np.asarray(dist, np.float64).ravel()[:LENS_COEFFICIENTS]
    d[: src.size] = src
    return d


@nb.njit(cache=True, inline="always")
def lens_radial(d, r2):
    """Numerator and denominator of the rational radial factor at ``r2 = x^2 + y^2``."""
    num = 1.0 + r2 * (d[0] + r2 * (d[1] + r2 * d[4]))
    den = 1.0 + r2 * (d[5] + r2 * (d[6] + r2 * d[7]))
    return num, den


@nb.njit(cache=True, inline="always")
def lens_distort(d, x, y):
    """OpenCV's distortion of normalised coordinates ``(x, y)``.

    Parameters
    ----------
    d : numpy.ndarray
        The 12 coefficients of :func:`lens_coefficients`.
    x, y : float or numpy.ndarray
        Undistorted normalised coordinates (arrays through ``lens_distort.py_func``).

    Returns
    -------
    tuple
        Distorted normalised coordinates ``(xd, yd)``.
    """
    p1, p2 = d[2], d[3]
    r2 = x * x + y * y
    num, den = lens_radial(d, r2)
    rad = num / den
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + d[8] * r2 + d[9] * r2 * r2
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + d[10] * r2 + d[11] * r2 * r2
    return xd, yd


@nb.njit(cache=True, inline="always")
def lens_distort_derivative(d, x, y, dx, dy):
    """:func:`lens_distort` and its derivative along a direction ``(dx, dy)``.

    Parameters
    ----------
    d : numpy.ndarray
        The 12 coefficients of :func:`lens_coefficients`.
    x, y : float
        Undistorted normalised coordinates.
    dx, dy : float
        Their derivative with respect to some parameter (the depth along a ray).

    Returns
    -------
    tuple
        ``(xd, yd, dxd, dyd)``: the distorted coordinates and their derivatives.
    """
    p1, p2, s1, s2, s3, s4 = d[2], d[3], d[8], d[9], d[10], d[11]
    r2 = x * x + y * y
    xd, yd = lens_distort(d, x, y)
    num, den = lens_radial(d, r2)
    rad = num / den
    dnum = d[0] + r2 * (2.0 * d[1] + 3.0 * r2 * d[4])
    dden = d[5] + r2 * (2.0 * d[6] + 3.0 * r2 * d[7])
    drad = (dnum * den - num * dden) / (den * den)  # d rad / d r2
    dr2 = 2 * (x * dx + y * dy)
    dxd = (
        dx * rad
        + x * drad * dr2
        + 2 * p1 * (dx * y + x * dy)
        + p2 * (dr2 + 4 * x * dx)
        + s1 * dr2
        + 2 * s2 * r2 * dr2
    )
    dyd = (
        dy * rad
        + y * drad * dr2
        + p1 * (dr2 + 4 * y * dy)
        + 2 * p2 * (dx * y + x * dy)
        + s3 * dr2
        + 2 * s4 * r2 * dr2
    )
    return xd, yd, dxd, dyd


def distort_normalized(x: np.ndarray, y: np.ndarray, dist: np.ndarray):
    """Apply the OpenCV distortion model (:func:`lens_distort`) to normalised coordinates.

    Supports k1, k2, p1, p2, k3, the rational k4..k6 and the thin prism s1..s4.
    (The tilted-sensor terms of the 14-coefficient model are not applied.)
    """
    return lens_distort.py_func(lens_coefficients(dist), x, y)


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
