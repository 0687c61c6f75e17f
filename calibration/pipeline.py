"""Offline calibration of a session folder: ``calibrate_session(path) -> (Rig, Report)``.

1. Board corners in the camera under all-white light (the brightest of the
   projectors' all-white frames of each pose).
2. Camera intrinsics from the corners; outlier poses are left out.
3. For each projector: decode the Gray code, map the corners into the
   projector through local homographies, calibrate its intrinsics as an
   inverse camera, then the camera-to-projector motion with the intrinsics held.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from lightflow.app.core.errors import CalibrationError, ConfigError
from lightflow.app.core.rig import CameraModel, ProjectorModel, Rig, rig_from_dict

from .corners import corners_to_projector, find_board_corners, window_size
from .gamma import measure_ramps
from .graycode import decode_graycode
from .report import DeviceReport, Report, placement_advice, tilt_warning
from .session import Session, load_grey, read_session
from .solve import (
    DEFAULT_FLAGS,
    Intrinsics,
    ProjectorViews,
    calibrate_robust,
    joint_refine,
    stereo_extrinsics,
)

MIN_POSES = 3
#: fewer good poses than this get a warning
GOOD_POSES = 6


def _rms(per_view) -> float:
    """Overall RMS from per-view RMS values (equal point counts assumed)."""
    a = np.asarray(per_view, float)
    return float(np.sqrt(np.mean(a**2))) if a.size else float("nan")


@dataclass(frozen=True)
class Options:
    """Calibration options.

    Attributes
    ----------
    flags : int
        OpenCV calibration flags for camera and projectors.
    outlier_factor : float
        A view is left out when its RMS exceeds this many times the median ...
    outlier_floor_px : float
        ... and this many pixels.
    min_corner_fraction : float
        Minimum fraction of board corners a projector must see in a pose.
    joint : bool
        Finish with a joint refinement of all devices and board poses.
    """

    flags: int = DEFAULT_FLAGS
    outlier_factor: float = 3.0
    outlier_floor_px: float = 0.25
    min_corner_fraction: float = 0.6
    joint: bool = True


def _camera_corners(session: Session, progress) -> tuple[dict, dict]:
    """Board corners per pose (name -> (n, 2)) and the reasons poses were skipped."""
    found, skipped = {}, {}
    for i, pose in enumerate(session.poses):
        white = None
        for proj in session.projectors:
            img = load_grey(session.root / pose.frames[proj.name][0],
                            session.frame_what(pose, proj, 0), session.camera_size)
            white = img if white is None else np.maximum(white, img)
        corners = find_board_corners(white, session.board)
        if corners is None:
            names = ", ".join(p.name for p in session.projectors)
            skipped[pose.name] = (f"board ({session.board.columns}x{session.board.rows} inner "
                                  f"corners) not found in the all-white frame (frame 0) of "
                                  f"projector {names}")
        else:
            found[pose.name] = corners
        if progress:
            progress("corners", i + 1, len(session.poses))
    return found, skipped


def calibrate_camera(
    corners: dict[str, np.ndarray],
    skipped: dict[str, str],
    object_points: np.ndarray,
    size: tuple[int, int],
    options: Options = Options(),
) -> tuple[Intrinsics, list[str], dict[str, str]]:
    """Camera intrinsics from the board corners of each pose, leaving out outlier poses.

    Parameters
    ----------
    corners : dict
        Pose name -> ``(n, 2)`` board corners in the camera.
    skipped : dict
        Pose name -> why its corners were not found (copied into the rejections).
    object_points : numpy.ndarray
        ``(n, 3)`` board corners in board coordinates.
    size : tuple of int
        Camera ``(width, height)``.

    Returns
    -------
    Intrinsics
        Calibration from the poses kept.
    used : list of str
        Names of the poses kept, in the order of ``Intrinsics.per_view``.
    rejected : dict
        Pose name -> why it was left out (``skipped`` plus the outliers).
    """
    names = list(corners)
    cam, keep = calibrate_robust([object_points] * len(names), [corners[n] for n in names], size,
                                 options.flags, options.outlier_factor, options.outlier_floor_px)
    rejected = dict(skipped)
    for n, k in zip(names, keep, strict=True):
        if not k:
            rejected[n] = (f"camera reprojection error over {options.outlier_factor:g}x the "
                           f"median (board moved or blurred?)")
    used = [n for n, k in zip(names, keep, strict=True) if k]
    return cam, used, rejected


def pose_warnings(n_good: int, normals: np.ndarray) -> list[str]:
    """Warnings about the poses: fewer than :data:`GOOD_POSES` good ones, too little tilt.

    Parameters
    ----------
    n_good : int
        Poses every device kept.
    normals : numpy.ndarray
        ``(n, 3)`` board normals (camera frame) of the poses the camera kept.
    """
    warnings = []
    if n_good < GOOD_POSES:
        warnings.append(f"only {n_good} good poses; use at least {GOOD_POSES} for a reliable "
                        f"calibration")
    tw = tilt_warning(normals)
    if tw:
        warnings.append(tw)
    return warnings


def calibrate_session(
    path: str | Path,
    options: Options = Options(),
    progress: Callable[[str, int, int], None] | None = None,
) -> tuple[Rig, Report]:
    """Calibrate the camera and projectors of a session folder.

    Parameters
    ----------
    path : str or pathlib.Path
        Session folder (formats.md section 4).
    options : Options
    progress : callable, optional
        ``progress(stage, i, n)``.

    Returns
    -------
    Rig
        Camera, projectors with ``R``, ``t`` (camera to projector) and patterns.
    Report
        Reprojection errors, left-out poses, warnings, placement advice and the
        projectors' gamma measured from ``CAL/gamma/`` (``None`` without that folder).

    Raises
    ------
    ConfigError, FrameError
        A malformed session (names the field, or the pose, projector and frame).
    CalibrationError
        Too few usable poses (names them and why).
    """
    session = read_session(path)
    obj_all = session.board.object_points()
    corners, skipped = _camera_corners(session, progress)
    if len(corners) < MIN_POSES:
        why = "; ".join(f"pose {k}: {v}" for k, v in skipped.items())
        raise CalibrationError(f"{session.root}: board found in {len(corners)} poses, need at "
                               f"least {MIN_POSES}: {why}")
    cam_size = session.camera_size
    cam, used, cam_rejected = calibrate_camera(corners, skipped, obj_all, cam_size, options)
    normals = np.array([cv2.Rodrigues(r)[0][:, 2] for r in cam.rvecs])

    win = window_size(cam_size[0])
    pose_by_name = {p.name: p for p in session.poses}
    projectors, reports, fits = [], [], []
    for proj in session.projectors:
        views, rejected = [], {}
        for i, n in enumerate(used):
            dec = decode_graycode(session.iter_frames(pose_by_name[n], proj), proj.width,
                                  proj.height)
            pts, ok = corners_to_projector(corners[n], dec.proj, dec.valid, win)
            if ok.mean() < options.min_corner_fraction:
                rejected[n] = (f"projector {proj.name} lights only {ok.sum()} of {len(ok)} board "
                               f"corners with decodable Gray code (frames 2..)")
            else:
                views.append((n, obj_all[ok], corners[n][ok], pts[ok], np.flatnonzero(ok)))
            if progress:
                progress(f"projector {proj.name}", i + 1, len(used))
        if len(views) < MIN_POSES:
            why = "; ".join(f"pose {k}: {v}" for k, v in rejected.items())
            raise CalibrationError(f"{session.root}: projector {proj.name}: {len(views)} usable "
                                   f"poses, need at least {MIN_POSES}: {why}")
        intr, pkeep = calibrate_robust([v[1] for v in views], [v[3] for v in views],
                                       (proj.width, proj.height), options.flags,
                                       options.outlier_factor, options.outlier_floor_px)
        for v, k in zip(views, pkeep, strict=True):
            if not k:
                rejected[v[0]] = (f"projector {proj.name} reprojection error over 3x the median "
                                  f"(bad decoding?)")
        views = [v for v, k in zip(views, pkeep, strict=True) if k]
        ext = stereo_extrinsics([v[1] for v in views], [v[2] for v in views],
                                [v[3] for v in views], cam, intr, cam_size)
        fits.append((proj, intr, ext, views, rejected))

    cam_K, cam_dist = cam.K, cam.dist
    cam_per_view = cam.per_view
    if options.joint:
        index = {n: i for i, n in enumerate(used)}
        pviews = []
        for _, intr, ext, views, _ in fits:
            vv = []
            for v in views:
                mask = np.zeros(len(obj_all), bool)
                mask[v[4]] = True
                vv.append((index[v[0]], mask, v[3]))
            pviews.append(ProjectorViews(intr.K, intr.dist, ext.R, ext.t, vv))
        joint = joint_refine(obj_all, [corners[n] for n in used], cam.rvecs, cam.tvecs, cam,
                             pviews)
        cam_K, cam_dist, cam_per_view = joint.camera_K, joint.camera_dist, joint.camera_per_view
    for j, (proj, intr, ext, views, rejected) in enumerate(fits):
        if options.joint:
            K, dist, R, t = joint.projectors[j]
            per_view, fit_rms = joint.projector_per_view[j], _rms(joint.projector_per_view[j])
        else:
            K, dist, R, t = intr.K, intr.dist, ext.R, ext.t
            per_view, fit_rms = intr.per_view, ext.rms
        projectors.append(ProjectorModel(proj.name, proj.width, proj.height, K, dist, R, t,
                                         proj.patterns))
        reports.append(DeviceReport(
            proj.name, _rms(per_view),
            {v[0]: float(e) for v, e in zip(views, per_view, strict=True)},
            rejected, fit_rms,
        ))
    cam_report = DeviceReport("camera", _rms(cam_per_view),
                              dict(zip(used, map(float, cam_per_view), strict=True)),
                              cam_rejected)

    rig = Rig(CameraModel(cam_size[0], cam_size[1], cam_K, cam_dist), tuple(projectors))
    try:
        rig = rig_from_dict(rig.to_dict(), "calibrated rig")
    except ConfigError as exc:  # pragma: no cover - guarded by session validation
        raise CalibrationError(str(exc)) from None
    n_good = min([len(used)] + [len(r.per_view) for r in reports])
    warnings = pose_warnings(n_good, normals)
    report = Report(cam_report, reports, len(session.poses), warnings, placement_advice(rig),
                    gamma=measure_ramps(session.root))
    return rig, report
