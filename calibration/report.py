"""Calibration report, comparison with ground truth and plain-words placement advice."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lightflow.app.core.rig import Rig

from .gamma import Response, gamma_lines

#: accuracy bars of a simulated 1600x1200 session (issue 4)
BARS = {"focal_pct": 0.5, "principal_px": 3.0, "position_mm": 3.0, "rotation_deg": 0.2,
        "rms_px": 0.3}


@dataclass
class DeviceReport:
    """Reprojection errors of one device (the camera or a projector).

    Attributes
    ----------
    name : str
    rms : float
        Overall RMS reprojection error of its intrinsic calibration (pixels).
    per_view : dict
        Pose name -> RMS error (pixels) of the views used.
    rejected : dict
        Pose name -> reason, for the views left out.
    stereo_rms : float or None
        RMS of the camera-to-projector fit (projectors only).
    """

    name: str
    rms: float
    per_view: dict[str, float]
    rejected: dict[str, str] = field(default_factory=dict)
    stereo_rms: float | None = None


@dataclass
class Report:
    """What calibration found, in plain words and numbers."""

    camera: DeviceReport
    projectors: list[DeviceReport]
    poses_total: int
    warnings: list[str] = field(default_factory=list)
    placement: list[str] = field(default_factory=list)
    comparison: dict[str, Any] | None = None
    #: projector name -> measured response (or why not), None when no grey ramp was captured
    gamma: dict[str, Response | str] | None = None

    @property
    def rms(self) -> float:
        """Worst overall RMS reprojection error of any device."""
        vals = [self.camera.rms] + [p.rms for p in self.projectors]
        vals += [p.stereo_rms for p in self.projectors if p.stereo_rms is not None]
        return max(vals)

    def summary_lines(self) -> list[str]:
        lines = []
        for dev in [self.camera, *self.projectors]:
            kind = "camera" if dev is self.camera else f"projector {dev.name}"
            extra = f", camera+projector fit {dev.stereo_rms:.3f} px" if dev.stereo_rms else ""
            lines.append(f"{kind}: RMS reprojection error {dev.rms:.3f} px over "
                         f"{len(dev.per_view)} of {self.poses_total} poses{extra}")
            views = "  ".join(f"{k} {v:.3f}" for k, v in dev.per_view.items())
            lines.append(f"  per pose (px): {views}")
            for pose, why in dev.rejected.items():
                lines.append(f"  left out {pose}: {why}")
        lines += gamma_lines(self.gamma)
        for w in self.warnings:
            lines.append(f"warning: {w}")
        lines += self.placement
        if self.comparison is not None:
            lines += comparison_lines(self.comparison)
        return lines


def _angle_deg(R: np.ndarray) -> float:
    c = (np.trace(R) - 1) / 2
    return math.degrees(math.acos(float(np.clip(c, -1, 1))))


def _intrinsics_errors(K: np.ndarray, K_true: np.ndarray) -> dict[str, float]:
    return {
        "fx_pct": 100 * abs(K[0, 0] / K_true[0, 0] - 1),
        "fy_pct": 100 * abs(K[1, 1] / K_true[1, 1] - 1),
        "cx_px": abs(K[0, 2] - K_true[0, 2]),
        "cy_px": abs(K[1, 2] - K_true[1, 2]),
    }


def compare_rigs(estimated: Rig, truth: Rig) -> dict[str, Any]:
    """Errors of a calibrated rig against the true one.

    Returns
    -------
    dict
        ``camera`` and ``projectors[name]`` with ``fx_pct``, ``fy_pct``
        (relative focal errors in percent), ``cx_px``, ``cy_px`` (principal
        point errors), and for projectors ``position_mm`` (centre of projection
        in camera coordinates) and ``rotation_deg``; ``worst`` collects the
        largest of each kind and ``pass`` tells whether :data:`BARS` are met.
    """
    out: dict[str, Any] = {"camera": _intrinsics_errors(estimated.camera.K, truth.camera.K),
                           "projectors": {}}
    true_by_name = {p.name: p for p in truth.projectors}
    for p in estimated.projectors:
        t = true_by_name.get(p.name)
        if t is None:
            continue
        e = _intrinsics_errors(p.K, t.K)
        e["position_mm"] = 1000 * float(np.linalg.norm(p.centre_in_camera - t.centre_in_camera))
        e["rotation_deg"] = _angle_deg(p.R @ t.R.T)
        out["projectors"][p.name] = e
    devs = [out["camera"], *out["projectors"].values()]
    worst = {
        "focal_pct": max(max(d["fx_pct"], d["fy_pct"]) for d in devs),
        "principal_px": max(max(d["cx_px"], d["cy_px"]) for d in devs),
        "position_mm": max((d["position_mm"] for d in out["projectors"].values()), default=0.0),
        "rotation_deg": max((d["rotation_deg"] for d in out["projectors"].values()),
                            default=0.0),
    }
    out["worst"] = worst
    out["pass"] = all(worst[k] <= BARS[k] for k in worst)
    return out


def comparison_lines(cmp: dict[str, Any]) -> list[str]:
    """Plain lines of a :func:`compare_rigs` result."""
    lines = ["against ground truth:"]
    for name, d in [("camera", cmp["camera"]), *((f"projector {k}", v)
                                                 for k, v in cmp["projectors"].items())]:
        s = (f"  {name}: focal {d['fx_pct']:.3f} % / {d['fy_pct']:.3f} %, principal point "
             f"{d['cx_px']:.2f} / {d['cy_px']:.2f} px")
        if "position_mm" in d:
            s += f", position {d['position_mm']:.2f} mm, rotation {d['rotation_deg']:.3f} deg"
        lines.append(s)
    w = cmp["worst"]
    lines.append(
        f"  worst: focal {w['focal_pct']:.3f} % (bar {BARS['focal_pct']}), principal point "
        f"{w['principal_px']:.2f} px (bar {BARS['principal_px']}), position "
        f"{w['position_mm']:.2f} mm (bar {BARS['position_mm']}), rotation "
        f"{w['rotation_deg']:.3f} deg (bar {BARS['rotation_deg']}): "
        f"{'within' if cmp['pass'] else 'OUTSIDE'} the bars"
    )
    return lines


def tilt_warning(normals: np.ndarray, min_range_deg: float = 20.0) -> str | None:
    """A warning when board poses lack tilt about either image axis.

    Parameters
    ----------
    normals : numpy.ndarray
        ``(n, 3)`` board normals in camera coordinates.
    """
    n = normals * np.sign(normals[:, 2:3] + 1e-12)
    about_vertical = np.degrees(np.arctan2(n[:, 0], n[:, 2]))
    about_horizontal = np.degrees(np.arctan2(n[:, 1], n[:, 2]))
    rv = float(np.ptp(about_vertical))
    rh = float(np.ptp(about_horizontal))
    if rv >= min_range_deg and rh >= min_range_deg:
        return None
    return (f"poses lack tilt variety: the board turned over {rv:.0f} deg left-right and "
            f"{rh:.0f} deg up-down; turn it by 20-40 deg both ways about both axes "
            f"(at least {min_range_deg:.0f} deg range each)")


def placement_advice(rig: Rig, min_depth_gap_m: float = 0.1,
                     min_axis_angle_deg: float = 10.0) -> list[str]:
    """Plain-words advice when two projectors sit side by side, pointing alike.

    With the projectors' centres at about the same distance along the camera's
    viewing direction and their axes nearly parallel, the ratio of the two
    light flows hardly changes with depth (paper: "bad setup"), so depth is
    poorly conditioned.
    """
    if len(rig.projectors) != 2:
        return []
    a, b = rig.projectors
    ca, cb = a.centre_in_camera, b.centre_in_camera
    axis_a, axis_b = a.R.T @ np.array([0, 0, 1.0]), b.R.T @ np.array([0, 0, 1.0])
    angle = math.degrees(math.acos(float(np.clip(axis_a @ axis_b, -1, 1))))
    gap = abs(ca[2] - cb[2])
    if gap >= min_depth_gap_m or angle >= min_axis_angle_deg:
        return []
    # move the projector that is further to the side forward: it keeps its view of the scene
    mover = a if abs(ca[0]) >= abs(cb[0]) else b
    c = mover.centre_in_camera
    side = "right" if c[0] > 0 else "left"
    move = max(0.2, 0.25 - gap)
    return [
        f"placement: projectors {a.name!r} and {b.name!r} are at nearly the same distance along "
        f"the camera's viewing direction ({gap:.2f} m apart) and point nearly parallel "
        f"({angle:.0f} deg apart); the ratio of their light flows then hardly changes with "
        f"depth.",
        f"placement: move projector {mover.name!r} (on the camera's {side}) about {move:.1f} m "
        f"towards the scene and turn it {20:.0f}-{30:.0f} deg towards the camera's axis, "
        f"then calibrate again.",
    ]


def rigcheck_lines(rig: Rig) -> list[str]:
    """Lines of the lead's placement check, if :mod:`lightflow.app.rigcheck` exists."""
    try:
        from lightflow.app.rigcheck import check_rig
    except ImportError:
        return ["placement check: lightflow.app.rigcheck is not available, skipped"]
    result = check_rig(rig)
    lines = list(result.summary_lines())
    lines += [f"warning: {w}" for w in getattr(result, "warnings", [])
              if f"warning: {w}" not in lines]
    return lines
