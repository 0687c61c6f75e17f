"""Where a depth error comes from: each stage against the renderer's true flows.

The simulator knows every surface at every instant.  From its ground truth at
the start, middle and end of an exposure, :func:`true_flows` derives what the
pipeline measures, per pixel and pattern: the sweep of the line along the
camera row (camera px), the local line interval (camera px) and the flow
(projector px).  :func:`stage_errors` then compares the pipeline's flows and
log ratio with them on the moving pixels, so that an error in depth can be
traced to one pattern's flow (its band length or its interval) or to the
ratio.

The projection here is OpenCV's own (``cv2.projectPoints``), not the core's
lens model, so an error in the core's geometry shows instead of cancelling.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from .core.errors import ConfigError
from .core.patterns import local_pitch
from .core.rig import Rig

#: file of the true flows of a frame, beside its ground truth
FLOWS_SUFFIX = "_flows.npz"
#: the maps of a true-flows file
MAPS = ("sweep", "interval", "flow", "line")


@dataclass(frozen=True)
class TrueFlows:
    """What the pipeline should measure in one frame, per pattern (``(2, H, W)`` float32).

    Attributes
    ----------
    sweep : numpy.ndarray
        Length of the swept line along the camera row (camera px): the band
        length minus the line width, without blur.
    interval : numpy.ndarray
        Distance between neighbouring lines along the camera row (camera px).
    flow : numpy.ndarray
        Motion of the lit point across the exposure, in projector pixels.
    line : numpy.ndarray
        Width of the projected line along the camera row (camera px).

    NaN where the pixel does not see one moving surface for the whole exposure
    (an edge passes it), or the pattern does not light it.
    """

    sweep: np.ndarray
    interval: np.ndarray
    flow: np.ndarray
    line: np.ndarray

    def save(self, path: str | Path) -> None:
        """Write as a compressed ``.npz`` (``sweep``, ``interval``, ``flow``, ``line``)."""
        np.savez_compressed(path, sweep=self.sweep, interval=self.interval, flow=self.flow,
                            line=self.line)  # fmt: skip

    @staticmethod
    def load(path: str | Path) -> TrueFlows:
        """Read a file written by :meth:`save`; one ConfigError line when it is not one."""
        try:
            with np.load(path) as d:
                maps = [np.asarray(d[k], np.float32) for k in MAPS]
        except (OSError, KeyError, ValueError) as exc:
            raise ConfigError(
                f"{path}: expected true flows ({', '.join(MAPS)}): {exc}"
            ) from None
        if not (maps[0].ndim == 3 and all(m.shape == maps[0].shape for m in maps)):
            raise ConfigError(f"{path}: {', '.join(MAPS)} must be (2, H, W) maps alike")
        return TrueFlows(*maps)


def _projector_columns(rig: Rig, points: np.ndarray) -> np.ndarray:
    """``(P, H, W)`` projector column lighting each camera-frame point (NaN where none)."""
    h, w = points.shape[:2]
    flat = np.ascontiguousarray(points.reshape(-1, 3), dtype=np.float64)
    ok = np.isfinite(flat).all(axis=1)
    out = np.full((len(rig.patterns), h * w), np.nan)
    for q, (proj, _pat) in enumerate(rig.patterns):
        rvec, _ = cv2.Rodrigues(np.asarray(proj.R, np.float64))
        # in front of the projector only: projectPoints would mirror points behind it
        front = ok & ((flat @ np.asarray(proj.R).T + proj.t)[:, 2] > 1e-6)
        if not front.any():
            continue
        uv, _ = cv2.projectPoints(flat[front].reshape(-1, 1, 3), rvec,
                                  np.asarray(proj.t, np.float64), np.asarray(proj.K, np.float64),
                                  np.asarray(proj.dist, np.float64))  # fmt: skip
        out[q, front] = uv[:, 0, 0]
    return out.reshape(len(rig.patterns), h, w)


def flows_from_truth(rig: Rig, rays: np.ndarray, start, middle, end) -> TrueFlows:
    """True sweeps, intervals and flows from the ground truth at three instants.

    Parameters
    ----------
    rig : Rig
    rays : numpy.ndarray
        ``(H, W, 3)`` camera rays with z = 1, from OpenCV's undistortion (the
        simulator's own, :attr:`SceneRenderer.rays`).
    start, middle, end : GroundTruth
        Truth at the start, middle and end of the exposure.

    Returns
    -------
    TrueFlows
    """
    cols = [_projector_columns(rig, rays * g.depth[..., None].astype(np.float64))
            for g in (start, middle, end)]  # fmt: skip
    # one moving surface at this pixel for the whole exposure
    same = ((start.object_id == middle.object_id) & (end.object_id == middle.object_id)
            & (middle.object_id >= 2))  # fmt: skip
    # projector columns per camera column on the surface, at mid-exposure
    du_dx = np.gradient(cols[1], axis=2)
    # the gradient straddles a depth edge there: no interval
    edge = np.zeros_like(same)
    edge[:, 1:-1] = (middle.object_id[:, :-2] != middle.object_id[:, 1:-1]) | (
        middle.object_id[:, 2:] != middle.object_id[:, 1:-1])
    ok = same & ~edge
    flow = np.abs(cols[2] - cols[0])
    with np.errstate(divide="ignore", invalid="ignore"):
        sweep = flow / np.abs(du_dx)
        # the pitch at the lit column (an exp2 pattern's pitch changes across it)
        pitch = np.stack([local_pitch(pat, proj.width, np.nan_to_num(cols[1][q]))
                          for q, (proj, pat) in enumerate(rig.patterns)])  # fmt: skip
        interval = pitch / np.abs(du_dx)
        widths = np.array([pat.width_px for _, pat in rig.patterns])[:, None, None]
        line = widths / np.abs(du_dx)
    maps = []
    for m in (sweep, interval, flow, line):
        m = np.where(ok[None] & np.isfinite(m), m, np.nan).astype(np.float32)
        maps.append(m)
    return TrueFlows(*maps)


def true_flows(renderer, t0: float, exposure_s: float) -> TrueFlows:
    """True flows of one frame (exposure from ``t0``), from the simulator's ground truth.

    Parameters
    ----------
    renderer : SceneRenderer
        The scene and rig (:class:`lightflow.drivers.sim.synthetic.SceneRenderer`).
    t0, exposure_s : float
        Start and length of the exposure (s).
    """
    r = renderer
    return flows_from_truth(r.rig, r.rays, r.truth(t0), r.truth(t0 + 0.5 * exposure_s),
                            r.truth(t0 + exposure_s))  # fmt: skip


def stage_errors(flows_grid, log_ratio_grid, depth, truth, flows: TrueFlows, stride: int,
                 single: bool, causes_grid=None, intervals_grid=None) -> dict:  # fmt: skip
    """Per-pixel errors of each stage on the moving pixels that got a depth.

    Parameters
    ----------
    flows_grid : list of numpy.ndarray
        The pipeline's flows per pattern (projector px) on the analysis grid.
    log_ratio_grid : numpy.ndarray
        The pipeline's smoothed log flow ratio on the grid.
    depth : numpy.ndarray
        ``(H, W)`` estimated depth.
    truth : GroundTruth
        Truth at mid-exposure.
    flows : TrueFlows
    stride : int
    single : bool
        One projector: the log ratio is that of the intervals, not of the flows.
    causes_grid : numpy.ndarray, optional
        The pipeline's cause per grid pixel: the moving pixels without depth are
        listed with their cause and their true sweep over the line width.
    intervals_grid : numpy.ndarray, optional
        ``(2, h, w)`` measured line intervals: each flow's error is split into
        that of the interval and that of the band length.

    Returns
    -------
    dict
        Arrays over the same pixels: ``flow_rel`` (2, n) measured/true - 1 per
        pattern, ``log_ratio`` (n,) measured - true, ``depth`` (n,) signed
        error (m), and the true ``sweep``/``interval`` (2, n) in camera px;
        ``missed_cause`` and ``missed_sweep_over_line`` (the smaller of the
        patterns) for the moving pixels without depth.
    """
    gh, gw = log_ratio_grid.shape
    ys = np.arange(gh) * stride + (stride - 1) // 2
    xs = np.arange(gw) * stride + (stride - 1) // 2
    sub = np.ix_(ys, xs)
    measured = np.stack([np.asarray(f, np.float64) for f in flows_grid])
    tf = flows.flow[(slice(None), *sub)].astype(np.float64)
    tb = flows.interval[(slice(None), *sub)].astype(np.float64)
    ts = flows.sweep[(slice(None), *sub)].astype(np.float64)
    z = depth[sub].astype(np.float64)
    zt = truth.depth[sub].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        # the pipeline's ratio is of the sweeps in line intervals (L / B), and with one
        # projector that of the intervals
        true_lr = np.log(tb[1] / tb[0]) if single else np.log((ts[0] / tb[0]) / (ts[1] / tb[1]))
        on = (np.isfinite(measured).all(axis=0) & np.isfinite(tf).all(axis=0)
              & (tf > 0).all(axis=0) & np.isfinite(z) & np.isfinite(zt)
              & np.isfinite(log_ratio_grid) & np.isfinite(true_lr))  # fmt: skip
        tl = flows.line[(slice(None), *sub)].astype(np.float64)
        moving = np.isfinite(ts).all(axis=0) & np.isfinite(zt)
        missed = moving & ~np.isfinite(z)
        if causes_grid is None:
            causes_grid = np.zeros((gh, gw), np.uint8)
        return {
            "missed_cause": causes_grid[missed].astype(np.int64),
            "missed_sweep_over_line": np.min(ts[:, missed] / tl[:, missed], axis=0),
            "flow_rel": measured[:, on] / tf[:, on] - 1.0,
            "interval_rel": (np.asarray(intervals_grid, np.float64)[:, on] / tb[:, on] - 1.0
                             if intervals_grid is not None else np.full((2, on.sum()), np.nan)),
            "log_ratio": log_ratio_grid[on].astype(np.float64) - true_lr[on],
            "depth": z[on] - zt[on],
            "sweep": ts[:, on],
            "interval": tb[:, on],
        }


def summarise(per_frame: list[dict]) -> dict:
    """Pooled medians of :func:`stage_errors` over frames (NaN without pixels).

    Returns ``n``, per pattern the median signed and absolute relative flow
    error (%), the median true sweep and interval (camera px), and the median
    signed log-ratio and depth (mm) errors.
    """
    pooled = {k: np.concatenate([f[k] for f in per_frame], axis=-1) for k in per_frame[0]}
    n = pooled["depth"].size

    def med(v):
        return float(np.median(v)) if v.size else float("nan")

    out = {"n": n, "log_ratio": med(pooled["log_ratio"]), "depth_mm": 1e3 * med(pooled["depth"])}
    # why the moving pixels without depth got none, and how far their lines moved
    from .core.causes import CAUSES

    missed = {}
    for code in np.unique(pooled["missed_cause"]):
        sel = pooled["missed_cause"] == code
        missed[CAUSES[int(code)][0]] = (int(sel.sum()), med(pooled["missed_sweep_over_line"][sel]))
    out["missed"] = dict(sorted(missed.items(), key=lambda kv: -kv[1][0]))
    for p in range(2):
        out[f"flow{p}_signed_pct"] = 100 * med(pooled["flow_rel"][p])
        out[f"flow{p}_abs_pct"] = 100 * med(np.abs(pooled["flow_rel"][p]))
        # flow = (L / B) P: (1 + flow error) = (1 + length error) / (1 + interval error)
        b = pooled["interval_rel"][p]
        out[f"interval{p}_signed_pct"] = 100 * med(b)
        out[f"length{p}_signed_pct"] = 100 * med((1 + pooled["flow_rel"][p]) * (1 + b) - 1)
        out[f"sweep{p}_px"] = med(pooled["sweep"][p])
        out[f"interval{p}_px"] = med(pooled["interval"][p])
    return out


def format_stages(name: str, s: dict) -> str:
    """One line of :func:`summarise`'s figures."""
    if not s["n"]:
        return f"{name}: no moving pixel with depth to attribute{_missed(s)}"
    pats = "; ".join(
        f"pattern {p} flow {s[f'flow{p}_signed_pct']:+.1f} % (|.| {s[f'flow{p}_abs_pct']:.1f}), "
        f"sweep {s[f'length{p}_signed_pct']:+.1f} %, "
        f"interval {s[f'interval{p}_signed_pct']:+.1f} % "
        f"(true sweep {s[f'sweep{p}_px']:.1f} px of interval {s[f'interval{p}_px']:.1f})"
        for p in range(2)
    )
    return (f"{name}: {s['n']} px; {pats}; log ratio {s['log_ratio']:+.3f}; depth "
            f"{s['depth_mm']:+.1f} mm{_missed(s)}")  # fmt: skip


def _missed(s: dict) -> str:
    top = list(s["missed"].items())[:4]
    parts = [f"{name} {n} px (true sweep {r:.1f} line widths)" for name, (n, r) in top]
    return "; no depth: " + ", ".join(parts) if parts else ""
