"""Camera and projector geometry with the full OpenCV lens model (numpy, OpenCV, numba).

The core's lens model is written once, here: :func:`lens_distort` and its
derivative :func:`lens_distort_derivative` work on the numbers of
:func:`lens_coefficients` (all 14 of OpenCV's coefficients).  The numpy
functions below call them on arrays, and the depth model's numba kernels
compile them in, so the depth table and the numpy projection cannot drift apart.  The
simulator does not use it: it projects with OpenCV itself, and a test checks
that the two agree.
"""

from __future__ import annotations

import cv2
import numpy as np
from numba.extending import register_jitable

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


#: numbers of the lens model: k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4, the
#: tilted sensor's 3x3 projection (row major), and 1 when that is not the identity
LENS_COEFFICIENTS = 22


def tilt_matrix(tau_x: float, tau_y: float) -> np.ndarray:
    """OpenCV's tilted-sensor projection (``computeTiltProjectionMatrix``) for angles in radians."""
    cx, sx, cy, sy = np.cos(tau_x), np.sin(tau_x), np.cos(tau_y), np.sin(tau_y)
    rot_x = np.array([[1.0, 0.0, 0.0], [0.0, cx, sx], [0.0, -sx, cx]])
    rot_y = np.array([[cy, 0.0, -sy], [0.0, 1.0, 0.0], [sy, 0.0, cy]])
    rot = rot_y @ rot_x
    proj_z = np.array([[rot[2, 2], 0.0, -rot[0, 2]], [0.0, rot[2, 2], -rot[1, 2]], [0, 0, 1.0]])
    return proj_z @ rot


def lens_coefficients(dist) -> np.ndarray:
    """The ``(22,)`` float64 numbers of :func:`lens_distort` from OpenCV's ``dist``.

    Parameters
    ----------
    dist : array_like
        OpenCV distortion coefficients (4, 5, 8, 12 or 14 of them; missing ones are 0).

    Returns
    -------
    numpy.ndarray
        k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4, the tilt matrix of the
        14-coefficient model's ``tau_x, tau_y`` (9, row major) and a flag, 1
        when the sensor is tilted.
    """
    d = np.zeros(LENS_COEFFICIENTS)
    src = np.asarray(dist, np.float64).ravel()
    d[: min(src.size, 12)] = src[:12]
    tau = src[12:14] if src.size >= 14 else np.zeros(2)
    d[12:21] = tilt_matrix(tau[0], tau[1]).ravel()
    d[21] = 1.0 if np.any(tau) else 0.0
    return d


# register_jitable: plain Python functions (numpy arrays work, nothing to compile)
# that numba kernels compile into themselves when they call them


@register_jitable
def _lens_radial(d, r2):
    """Numerator and denominator of the rational radial factor at ``r2 = x^2 + y^2``."""
    num = 1.0 + r2 * (d[0] + r2 * (d[1] + r2 * d[4]))
    den = 1.0 + r2 * (d[5] + r2 * (d[6] + r2 * d[7]))
    return num, den


@register_jitable
def _lens_untilted(d, x, y):
    """Radial, tangential and thin-prism distortion (the model before the sensor tilt)."""
    p1, p2 = d[2], d[3]
    r2 = x * x + y * y
    num, den = _lens_radial(d, r2)
    rad = num / den
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + d[8] * r2 + d[9] * r2 * r2
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + d[10] * r2 + d[11] * r2 * r2
    return xd, yd


@register_jitable
def lens_distort(d, x, y):
    """OpenCV's distortion of normalised coordinates ``(x, y)``.

    Parameters
    ----------
    d : numpy.ndarray
        The numbers of :func:`lens_coefficients`.
    x, y : float or numpy.ndarray
        Undistorted normalised coordinates (scalars in numba kernels).

    Returns
    -------
    tuple
        Distorted normalised coordinates ``(xd, yd)``.
    """
    xd, yd = _lens_untilted(d, x, y)
    if d[21] == 0.0:
        return xd, yd
    # tilted sensor: a projective map of the distorted coordinates
    w = d[18] * xd + d[19] * yd + d[20]
    return (d[12] * xd + d[13] * yd + d[14]) / w, (d[15] * xd + d[16] * yd + d[17]) / w


@register_jitable
def lens_distort_derivative(d, x, y, dx, dy):
    """:func:`lens_distort` and its derivative along a direction ``(dx, dy)``.

    Parameters
    ----------
    d : numpy.ndarray
        The numbers of :func:`lens_coefficients`.
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
    num, den = _lens_radial(d, r2)
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
    xd, yd = _lens_untilted(d, x, y)
    if d[21] == 0.0:
        return xd, yd, dxd, dyd
    # the tilt's projective map and its derivative (quotient rule)
    a = d[12] * xd + d[13] * yd + d[14]
    b = d[15] * xd + d[16] * yd + d[17]
    w = d[18] * xd + d[19] * yd + d[20]
    da = d[12] * dxd + d[13] * dyd
    db = d[15] * dxd + d[16] * dyd
    dw = d[18] * dxd + d[19] * dyd
    return a / w, b / w, (da * w - a * dw) / (w * w), (db * w - b * dw) / (w * w)


def distort_normalized(x: np.ndarray, y: np.ndarray, dist: np.ndarray):
    """Apply the OpenCV distortion model (:func:`lens_distort`) to normalised coordinates.

    Supports k1, k2, p1, p2, k3, the rational k4..k6, the thin prism s1..s4 and
    the tilted sensor tau_x, tau_y: all 14 coefficients.
    """
    return lens_distort(lens_coefficients(dist), x, y)


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
