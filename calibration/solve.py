"""Intrinsic and camera-to-projector calibration from corner correspondences.

OpenCV gives the initial per-device calibrations; SciPy's sparse robust
least squares refines them jointly.

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


@dataclass(frozen=True)
class ProjectorViews:
    """A projector's observations for :func:`joint_refine`.

    Attributes
    ----------
    K, dist, R, t : numpy.ndarray
        Initial intrinsics and camera-to-projector motion.
    views : list of (int, numpy.ndarray, numpy.ndarray)
        ``(pose index, bool mask over the board points, (m, 2) projector pixels)``.
    """

    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray
    views: list


@dataclass(frozen=True)
class JointResult:
    """Jointly refined camera, projectors and board poses."""

    camera_K: np.ndarray
    camera_dist: np.ndarray
    projectors: list  # (K, dist, R, t) per projector
    camera_per_view: np.ndarray
    projector_per_view: list  # per projector, RMS of each of its views
    rms: float


def _intr_vec(K, dist, n_dist):
    return np.concatenate([[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], dist[:n_dist]])


def _intr_mat(v, dist0, n_dist):
    K = np.array([[v[0], 0, v[2]], [0, v[1], v[3]], [0, 0, 1.0]])
    d = np.array(dist0, float).copy()
    d[:n_dist] = v[4 : 4 + n_dist]
    return K, d


def joint_refine(
    object_points: np.ndarray,
    camera_points: Sequence[np.ndarray],
    board_rvecs: Sequence[np.ndarray],
    board_tvecs: Sequence[np.ndarray],
    camera: Intrinsics,
    projectors: Sequence[ProjectorViews],
    n_dist: int = 4,
    iterations: int = 50,
    outlier_px: float = 1.0,
) -> JointResult:
    """Refine everything together: one board pose per view shared by all devices.

    A sparse, robust least-squares fit (``scipy.optimize.least_squares``, trust
    region with a soft-L1 loss) of camera intrinsics, each projector's
    intrinsics and motion, and the board poses, to the corners seen by the
    camera and mapped into the projectors.  Sharing the board poses lets the
    camera's observations constrain the projectors' intrinsics (and vice versa).

    Parameters
    ----------
    object_points : numpy.ndarray
        ``(n, 3)`` board points (the same for every view).
    camera_points : sequence of numpy.ndarray
        ``(n, 2)`` camera pixels per view.
    board_rvecs, board_tvecs : sequence of numpy.ndarray
        Initial board-to-camera poses per view.
    camera : Intrinsics
        Initial camera intrinsics.
    projectors : sequence of ProjectorViews
    n_dist : int
        Distortion coefficients refined (4: k1, k2, p1, p2; the rest stay fixed).
    iterations : int
        Jacobian evaluations allowed per parameter group (``max_nfev`` scales with it).
    outlier_px : float
        Residual (pixels) beyond which the soft-L1 loss grows linearly, so a few
        badly decoded corners cannot pull the fit.

    Returns
    -------
    JointResult
        RMS errors are of the plain (not robustified) residuals.
    """
    from scipy.optimize import least_squares
    from scipy.sparse import lil_matrix

    from lightflow.app.core.geometry import project_points

    obj = np.asarray(object_points, float)
    n = len(obj)
    n_views = len(camera_points)
    ni = 4 + n_dist
    cam_obs = np.concatenate([np.asarray(c, float).reshape(-1, 2) for c in camera_points])
    p0 = [_intr_vec(camera.K, camera.dist, n_dist)]
    for pj in projectors:
        p0 += [_intr_vec(pj.K, pj.dist, n_dist), cv2.Rodrigues(pj.R)[0].ravel(), pj.t.ravel()]
    for rv, tv in zip(board_rvecs, board_tvecs, strict=True):
        p0 += [np.ravel(rv), np.ravel(tv)]
    p0 = np.concatenate(p0).astype(float)
    off_pose = ni + len(projectors) * (ni + 6)
    proj_obs = [
        np.concatenate([np.asarray(q, float).reshape(-1, 2) for _, _, q in pj.views])
        if pj.views else np.zeros((0, 2))
        for pj in projectors
    ]

    def unpack(p):
        Kc, dc = _intr_mat(p[:ni], camera.dist, n_dist)
        projs = []
        for j, pj in enumerate(projectors):
            o = ni + j * (ni + 6)
            K, d = _intr_mat(p[o : o + ni], pj.dist, n_dist)
            rv, tv = p[o + ni : o + ni + 3], p[o + ni + 3 : o + ni + 6]
            projs.append((K, d, cv2.Rodrigues(rv)[0], tv))
        poses = [(cv2.Rodrigues(p[off_pose + 6 * i : off_pose + 6 * i + 3])[0],
                  p[off_pose + 6 * i + 3 : off_pose + 6 * i + 6]) for i in range(n_views)]
        return Kc, dc, projs, poses

    def residuals(p):
        Kc, dc, projs, poses = unpack(p)
        Xc = np.stack([obj @ R.T + t for R, t in poses])  # (views, n, 3)
        res = [(project_points(Kc, dc, Xc).reshape(-1, 2) - cam_obs).ravel()]
        for (K, d, R, t), pj, obs in zip(projs, projectors, proj_obs, strict=True):
            if not pj.views:
                continue
            pts = np.concatenate([Xc[i][m] for i, m, _ in pj.views]) @ R.T + t
            res.append((project_points(K, d, pts) - obs).ravel())
        return np.concatenate(res)

    # Which parameters each residual depends on: its device's intrinsics (and
    # motion, for a projector) and the board pose of its view.  Finite
    # differences then cost a few residual evaluations instead of one per parameter.
    n_res = 2 * n * n_views + sum(2 * len(o) for o in proj_obs)
    sparsity = lil_matrix((n_res, len(p0)), dtype=np.int8)
    for i in range(n_views):
        rows = slice(2 * n * i, 2 * n * (i + 1))
        sparsity[rows, :ni] = 1
        sparsity[rows, off_pose + 6 * i : off_pose + 6 * i + 6] = 1
    row = 2 * n * n_views
    for j, pj in enumerate(projectors):
        o = ni + j * (ni + 6)
        for i, m, _ in pj.views:
            k = 2 * int(np.count_nonzero(m))
            sparsity[row : row + k, o : o + ni + 6] = 1
            sparsity[row : row + k, off_pose + 6 * i : off_pose + 6 * i + 6] = 1
            row += k

    fit = least_squares(
        residuals, p0, jac_sparsity=sparsity, method="trf", loss="soft_l1",
        f_scale=outlier_px, x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12,
        max_nfev=iterations * 20,
    )
    p = fit.x
    r = residuals(p)
    cost = float(r @ r)
    Kc, dc, projs, _ = unpack(p)
    cam_res = r[: n_views * n * 2].reshape(n_views, n, 2)
    cam_pv = np.sqrt((cam_res**2).sum(-1).mean(-1))
    proj_pv = []
    o = n_views * n * 2
    for pj in projectors:
        pv = []
        for _, m, _ in pj.views:
            k = int(m.sum()) * 2
            e = r[o : o + k].reshape(-1, 2)
            pv.append(float(np.sqrt((e**2).sum(-1).mean())))
            o += k
        proj_pv.append(np.array(pv))
    rms = float(np.sqrt(cost / (len(r) / 2)))
    return JointResult(Kc, dc, projs, cam_pv, proj_pv, rms)
