"""Intrinsic and camera-to-projector calibration from corner correspondences (pure OpenCV).

Projectors are calibrated as inverse cameras: their "image points" are the
board corners mapped into projector pixels (see :mod:`.corners`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

#: k1, k2, p1, p2 estimated; k3 fixed at 0 (a 6-10 pose session cannot pin it down)
DEFAULT_FLAGS = cv2.CALIB_FIX_K3
_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)


@dataclass(frozen=True)
class Intrinsics:
    """Result of an intrinsic calibration.

    Attributes
    ----------
    K, dist : numpy.ndarray
        Camera matrix and 5 distortion coefficients.
    rms : float
        Overall RMS reprojection error (pixels).
    per_view : numpy.ndarray
        RMS reprojection error of each view used.
    rvecs, tvecs : list of numpy.ndarray
        Board pose of each view (board to device).
    """

    K: np.ndarray
    dist: np.ndarray
    rms: float
    per_view: np.ndarray
    rvecs: list
    tvecs: list


@dataclass(frozen=True)
class Extrinsics:
    """Rigid motion from camera to projector, ``X_proj = R @ X_cam + t``."""

    R: np.ndarray
    t: np.ndarray
    rms: float
    per_view: np.ndarray  # (n, 2): camera, projector RMS of each view


def _as_lists(object_points, image_points):
    obj = [np.ascontiguousarray(o, np.float32).reshape(-1, 1, 3) for o in object_points]
    img = [np.ascontiguousarray(p, np.float32).reshape(-1, 1, 2) for p in image_points]
    return obj, img


def calibrate_intrinsics(
    object_points: Sequence[np.ndarray],
    image_points: Sequence[np.ndarray],
    size: tuple[int, int],
    flags: int = DEFAULT_FLAGS,
) -> Intrinsics:
    """Calibrate one camera (or projector) from several views of a planar board.

    Parameters
    ----------
    object_points : sequence of numpy.ndarray
        ``(n_i, 3)`` board points of each view.
    image_points : sequence of numpy.ndarray
        ``(n_i, 2)`` their pixels.
    size : tuple of int
        ``(width, height)`` of the device image.
    flags : int
        OpenCV calibration flags.
    """
    obj, img = _as_lists(object_points, image_points)
    rms, K, dist, rvecs, tvecs, _, _, per_view = cv2.calibrateCameraExtended(
        obj, img, tuple(size), None, None, flags=flags, criteria=_CRITERIA
    )
    return Intrinsics(K, dist.ravel()[:5].copy(), float(rms), per_view.ravel().copy(),
                      list(rvecs), list(tvecs))


def outlier_views(per_view: np.ndarray, factor: float = 3.0, floor_px: float = 0.25) -> np.ndarray:
    """Bool mask of views whose RMS exceeds ``max(factor * median, floor_px)``."""
    per_view = np.asarray(per_view, float)
    if len(per_view) < 3:
        return np.zeros(len(per_view), bool)
    return per_view > max(factor * float(np.median(per_view)), floor_px)


def calibrate_robust(
    object_points: Sequence[np.ndarray],
    image_points: Sequence[np.ndarray],
    size: tuple[int, int],
    flags: int = DEFAULT_FLAGS,
    factor: float = 3.0,
    floor_px: float = 0.25,
    min_views: int = 3,
) -> tuple[Intrinsics, np.ndarray]:
    """:func:`calibrate_intrinsics`, dropping outlier views and recalibrating.

    Returns
    -------
    Intrinsics
        Calibration from the kept views.
    keep : numpy.ndarray
        Bool mask over the input views.
    """
    keep = np.ones(len(object_points), bool)
    while True:
        idx = np.flatnonzero(keep)
        res = calibrate_intrinsics([object_points[i] for i in idx],
                                   [image_points[i] for i in idx], size, flags)
        bad = outlier_views(res.per_view, factor, floor_px)
        if not bad.any() or keep.sum() - bad.sum() < min_views:
            return res, keep
        keep[idx[bad]] = False


def stereo_extrinsics(
    object_points: Sequence[np.ndarray],
    camera_points: Sequence[np.ndarray],
    projector_points: Sequence[np.ndarray],
    camera: Intrinsics,
    projector: Intrinsics,
    camera_size: tuple[int, int],
) -> Extrinsics:
    """Camera-to-projector motion from views seen by both, intrinsics held fixed.

    Parameters
    ----------
    object_points, camera_points, projector_points : sequence of numpy.ndarray
        Board points and their camera and projector pixels, per view.
    camera, projector : Intrinsics
        Individual calibrations.
    camera_size : tuple of int
    """
    obj, cam = _as_lists(object_points, camera_points)
    _, prj = _as_lists(object_points, projector_points)
    out = cv2.stereoCalibrateExtended(
        obj, cam, prj, camera.K.copy(), camera.dist.copy(), projector.K.copy(),
        projector.dist.copy(), tuple(camera_size), None, None,
        flags=cv2.CALIB_FIX_INTRINSIC, criteria=_CRITERIA,
    )
    rms, R, T, per_view = out[0], out[5], out[6], out[-1]
    return Extrinsics(R, T.ravel(), float(rms), np.asarray(per_view).reshape(-1, 2))
