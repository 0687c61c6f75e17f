"""Accuracy of the depth pipeline against the ground truth of simulated recordings.

A simulated recording (``lightflow simulate``) holds, beside its frames,
``ground_truth/<frame stem>.npz`` (a :class:`~lightflow.drivers.sim.synthetic.GroundTruth`)
and ``ground_truth/scene.json``.  The metrics are pure numpy functions of a
depth map and its ground truth; :func:`evaluate_recording` replays a
recording through :class:`~lightflow.app.core.pipeline.DepthPipeline` and pools them.

Metrics
-------
coverage
    Of the pixels on a moving object (``object_id >= 2``) that every projector
    lights, the fraction that got a depth: the method cannot measure what a
    projector does not light, so those pixels do not count against it.
depth error
    ``|depth - true depth|`` on moving-object pixels that got a depth
    (median, mean, 90th percentile).
off_object
    Fraction of all depth pixels that are not on a moving object (static
    background, or nothing at all): the method measures motion, so these are
    false detections.  With one projector and static depth on, the static
    background is measured too (from its line intervals): depth there is not
    counted as off the object.
plane RMSE
    For planar scenes, the paper's metric: a plane is fitted (robustly) to the
    3D points of the estimate on each moving object, and the RMSE of the
    point-to-plane distances of all those points is reported.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from lightflow.app.core.errors import ConfigError
from lightflow.app.core.rig import Rig

TRUTH_DIR = "ground_truth"
SCENE_JSON = "scene.json"
SCENE_FORMAT = "lightflow-ground-truth/1"

#: Tukey biweight tuning constant (95 % efficiency for Gaussian residuals)
_TUKEY_C = 4.685
#: MAD to standard deviation for Gaussian residuals
_MAD_SCALE = 1.4826
#: an error this large (m) or larger is gross: a wrong line (one line off moves a depth
#: by 2-7 cm on the evaluation rigs) or a flow far off, not noise.  The median and even
#: the 90th percentile hide such errors when they are fewer than one pixel in ten.
GROSS_M = 0.02


@dataclass(frozen=True)
class FrameMetrics:
    """Accuracy of one depth map.

    Attributes
    ----------
    coverage : float
        Covered fraction of the moving pixels lit by every projector (NaN if none).
    median_error_m, mean_error_m, p90_error_m : float
        Absolute depth error on the moving object (NaN without any estimate there).
    median_signed_m : float
        Median of estimate minus truth: a bias shows here, not in the absolute error.
    gross : float
        Fraction of the depth pixels on the moving object that are :data:`GROSS_M` or
        more off (NaN without any estimate there).
    off_object : float
        Fraction of depth pixels that are not on a moving object (0 without depth).
    plane_rmse_m : float
        Point-to-plane RMSE for planar scenes, NaN otherwise or without rays.
    n_target, n_covered : int
        Moving pixels lit by all projectors, and how many of them got a depth.
    n_depth, n_off : int
        Pixels with a depth, and how many of them are off the moving objects.
    n_plane : int
        Points that entered the plane RMSE.
    n_sigma, n_within_1sigma, n_within_2sigma : int
        Depth pixels on the object with a predicted standard deviation, and how
        many of them are within one and two of it of the truth.
    target_causes : tuple of int
        Per :mod:`lightflow.app.core.causes` code, the target pixels (moving, lit by
        every projector) that got it: ``[0]`` those with a depth, the rest why not.
    errors : numpy.ndarray
        The per-pixel signed errors (estimate - truth, float32), for pooling over frames.
    """

    coverage: float
    median_error_m: float
    mean_error_m: float
    p90_error_m: float
    median_signed_m: float
    off_object: float
    plane_rmse_m: float
    n_target: int
    n_covered: int
    n_depth: int
    n_off: int
    n_plane: int
    errors: np.ndarray = field(repr=False, compare=False)
    n_sigma: int = 0
    n_within_1sigma: int = 0
    n_within_2sigma: int = 0
    target_causes: tuple = ()
    gross: float = math.nan


@dataclass(frozen=True)
class RecordingMetrics:
    """Accuracy over all frames of a simulated recording.

    Errors are pooled over the pixels of all frames (the median is the median
    of every per-pixel error, not a median of medians); coverage and
    off_object are pixel-weighted; the plane RMSE pools the squared distances
    of the per-frame fits (the board moves between frames).
    """

    path: str
    scene: str
    exposure_s: float
    frames: int
    stride: int
    coverage: float
    median_error_m: float
    mean_error_m: float
    p90_error_m: float
    median_signed_m: float
    off_object: float
    plane_rmse_m: float
    planar: bool
    per_frame: tuple[FrameMetrics, ...] = field(repr=False, compare=False)
    within_1sigma: float = math.nan
    within_2sigma: float = math.nan
    no_depth_causes: dict = field(default_factory=dict)
    stages: dict = field(default_factory=dict)
    gross: float = math.nan

    def to_dict(self) -> dict:
        """JSON-ready summary (NaN becomes null), with the per-frame figures."""
        d = {k: v for k, v in asdict(self).items() if k != "per_frame"}
        d["per_frame"] = [
            {k: v for k, v in asdict(m).items() if k != "errors"} for m in self.per_frame
        ]
        return _nan_to_none(d)


def _nan_to_none(value):
    if isinstance(value, dict):
        return {k: _nan_to_none(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_nan_to_none(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


# ----------------------------------------------------------------------------- planes


def fit_plane(points: np.ndarray, iterations: int = 20) -> tuple[np.ndarray, float]:
    """Robust total-least-squares plane through ``(n, 3)`` points.

    Iteratively reweighted: each pass fits the weighted plane by the smallest
    eigenvector of the weighted scatter, then reweights with Tukey's biweight
    on the residuals scaled by their MAD, so that stray estimates (band ends,
    object edges) do not tilt the plane.

    Returns
    -------
    normal : numpy.ndarray
        Unit normal ``(3,)``.
    offset : float
        ``d`` with ``normal @ x + d = 0`` on the plane.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 3:
        raise ValueError(f"fit_plane: expected (n >= 3, 3) points, got {pts.shape}")
    w = np.ones(len(pts))
    normal, offset = np.array([0.0, 0.0, 1.0]), 0.0
    for _ in range(iterations):
        centre = (w @ pts) / w.sum()
        d = pts - centre
        scatter = (d * w[:, None]).T @ d
        _, vecs = np.linalg.eigh(scatter)
        new_normal = vecs[:, 0]
        new_offset = -float(new_normal @ centre)
        converged = (
            abs(abs(new_normal @ normal) - 1) < 1e-12 and abs(abs(new_offset) - abs(offset)) < 1e-12
        )
        normal, offset = new_normal, new_offset
        r = pts @ normal + offset
        scale = _MAD_SCALE * float(np.median(np.abs(r)))
        if scale <= 0 or converged:
            break
        u = r / (_TUKEY_C * scale)
        w = np.where(np.abs(u) < 1, (1 - u * u) ** 2, 0.0)
        if np.count_nonzero(w) < 3:
            break
    return normal, offset


def plane_residuals(points: np.ndarray) -> np.ndarray:
    """Signed point-to-plane distances of ``(n, 3)`` points to their robust plane."""
    normal, offset = fit_plane(points)
    return np.asarray(points, dtype=np.float64) @ normal + offset


# ----------------------------------------------------------------------------- frames


def _all_lit_mask(truth, n_projectors: int | None) -> np.ndarray:
    if n_projectors is None:
        # every projector lights something in a simulated frame, so the union of
        # the bits present is the "all projectors" value
        full = int(np.bitwise_or.reduce(truth.lit, axis=None)) if truth.lit.size else 0
    else:
        full = (1 << n_projectors) - 1
    return truth.lit == full


def _target_mask(truth, n_projectors: int | None) -> np.ndarray:
    """The pixels coverage is counted on: moving (object id 2 and up), lit by every projector."""
    return (truth.object_id >= 2) & _all_lit_mask(truth, n_projectors)


def coverage(depth: np.ndarray, truth, n_projectors: int | None = None) -> float:
    """Share of the moving pixels lit by every projector that have a depth.

    The coverage of :func:`evaluate_frame` alone, without the error statistics
    (a live view logs it on every frame).

    Parameters
    ----------
    depth : numpy.ndarray
        ``(H, W)`` estimated z, NaN without estimate.
    truth : GroundTruth
    n_projectors : int, optional
        As in :func:`evaluate_frame`.

    Returns
    -------
    float
        NaN when no moving pixel is lit by every projector.
    """
    target = _target_mask(truth, n_projectors)
    n_target = int(np.count_nonzero(target))
    if not n_target:
        return math.nan
    return int(np.count_nonzero(np.isfinite(depth[target]))) / n_target


def evaluate_frame(
    depth: np.ndarray,
    truth,
    rays: np.ndarray | None = None,
    n_projectors: int | None = None,
    depth_std: np.ndarray | None = None,
    causes_grid: np.ndarray | None = None,
    stride: int = 1,
    background: bool = False,
) -> FrameMetrics:
    """Compare one depth map with its ground truth.

    Parameters
    ----------
    depth : numpy.ndarray
        ``(H, W)`` estimated z in metres, NaN without estimate.
    truth : GroundTruth
        ``depth``, ``object_id``, ``lit`` and ``planar`` of the same frame.
    rays : numpy.ndarray, optional
        ``(H, W, 3)`` camera rays with z = 1 (:func:`lightflow.app.core.geometry.camera_rays`);
        needed for the plane RMSE of planar scenes.
    n_projectors : int, optional
        Number of projectors of the rig; inferred from ``truth.lit`` when omitted.
    depth_std : numpy.ndarray, optional
        ``(H, W)`` predicted standard deviation of ``depth``: scored against the errors.
    causes_grid : numpy.ndarray, optional
        The pipeline's cause code per grid pixel (grid ``stride``): counted on the
        target pixels.
    stride : int
    background : bool
        Whether the pipeline measures the static background (object id 1) too
        (one projector, static depth): depth there is then not off the object.

    Returns
    -------
    FrameMetrics
    """
    depth = np.asarray(depth)
    if depth.shape != truth.depth.shape:
        raise ValueError(f"depth {depth.shape} and ground truth {truth.depth.shape} differ")
    has_depth = np.isfinite(depth)
    moving = truth.object_id >= 2
    target = _target_mask(truth, n_projectors)
    n_target = int(np.count_nonzero(target))
    n_covered = int(np.count_nonzero(target & has_depth))
    n_depth = int(np.count_nonzero(has_depth))
    scored = moving | (truth.object_id == 1) if background else moving
    n_off = int(np.count_nonzero(has_depth & ~scored))
    on_object = has_depth & moving & np.isfinite(truth.depth)
    errors = (depth[on_object] - truth.depth[on_object]).astype(np.float32)
    med, mean, p90, signed = _error_stats(errors)
    rmse, n_plane = math.nan, 0
    if truth.planar and rays is not None:
        sq = []
        for obj in np.unique(truth.object_id[on_object]):
            sel = on_object & (truth.object_id == obj)
            if np.count_nonzero(sel) >= 3:
                pts = rays[sel] * depth[sel, None].astype(np.float64)
                sq.append(plane_residuals(pts) ** 2)
        if sq:
            all_sq = np.concatenate(sq)
            rmse, n_plane = float(np.sqrt(all_sq.mean())), int(all_sq.size)
    n_sigma = n1 = n2 = 0
    if depth_std is not None:
        sd = depth_std[on_object]
        has = np.isfinite(sd)
        err = np.abs(errors[has])
        n_sigma = int(np.count_nonzero(has))
        n1 = int(np.count_nonzero(err <= sd[has]))
        n2 = int(np.count_nonzero(err <= 2.0 * sd[has]))
    target_causes: tuple = ()
    if causes_grid is not None:
        from lightflow.app.core.causes import count_causes

        ys, xs = np.nonzero(target)
        gh, gw = causes_grid.shape
        codes = causes_grid[np.minimum(ys // stride, gh - 1), np.minimum(xs // stride, gw - 1)]
        # the grid says "depth" where the full-resolution map may not (a cell's depth
        # covers only part of it beside cells without): count the target pixels by the
        # full-resolution depth
        codes = np.where(has_depth[ys, xs], 0, np.where(codes == 0, 255, codes))
        counted = count_causes(codes[codes != 255])
        counted[0] = n_covered
        target_causes = tuple(int(c) for c in counted)
    return FrameMetrics(
        n_sigma=n_sigma,
        n_within_1sigma=n1,
        n_within_2sigma=n2,
        target_causes=target_causes,
        gross=_gross_share(errors),
        coverage=n_covered / n_target if n_target else math.nan,
        median_error_m=med,
        mean_error_m=mean,
        p90_error_m=p90,
        median_signed_m=signed,
        off_object=n_off / n_depth if n_depth else 0.0,
        plane_rmse_m=rmse,
        n_target=n_target,
        n_covered=n_covered,
        n_depth=n_depth,
        n_off=n_off,
        n_plane=n_plane,
        errors=errors,
    )


def _gross_share(errors: np.ndarray) -> float:
    """Share of the errors at least :data:`GROSS_M` in size (NaN without any)."""
    if errors.size == 0:
        return math.nan
    return float(np.count_nonzero(np.abs(errors) >= GROSS_M) / errors.size)


def _error_stats(errors: np.ndarray) -> tuple[float, float, float, float]:
    """Median, mean and 90th percentile of the absolute errors, and the median signed error."""
    if errors.size == 0:
        return math.nan, math.nan, math.nan, math.nan
    signed = errors.astype(np.float64)
    e = np.abs(signed)
    return float(np.median(e)), float(e.mean()), float(np.percentile(e, 90)), float(
        np.median(signed)
    )


def pool_metrics(per_frame: list[FrameMetrics]) -> dict[str, float]:
    """Pool per-frame metrics: pixel-weighted fractions, pooled errors and plane distances."""
    n_target = sum(m.n_target for m in per_frame)
    n_depth = sum(m.n_depth for m in per_frame)
    errors = np.concatenate([m.errors for m in per_frame]) if per_frame else np.empty(0)
    med, mean, p90, signed = _error_stats(errors)
    n_plane = sum(m.n_plane for m in per_frame)
    sq = sum(m.plane_rmse_m**2 * m.n_plane for m in per_frame if m.n_plane)
    return {
        "coverage": sum(m.n_covered for m in per_frame) / n_target if n_target else math.nan,
        "median_error_m": med,
        "mean_error_m": mean,
        "p90_error_m": p90,
        "median_signed_m": signed,
        "gross": _gross_share(errors),
        "off_object": sum(m.n_off for m in per_frame) / n_depth if n_depth else 0.0,
        "plane_rmse_m": math.sqrt(sq / n_plane) if n_plane else math.nan,
        **_sigma_and_causes(per_frame, n_target),
    }


def _sigma_and_causes(per_frame: list[FrameMetrics], n_target: int) -> dict:
    """Shares within 1 and 2 predicted sigma; shares of the target pixels by cause."""
    from lightflow.app.core.causes import CAUSE_NAMES

    n_sigma = sum(m.n_sigma for m in per_frame)
    out = {
        "within_1sigma": sum(m.n_within_1sigma for m in per_frame) / n_sigma
        if n_sigma else math.nan,
        "within_2sigma": sum(m.n_within_2sigma for m in per_frame) / n_sigma
        if n_sigma else math.nan,
        "no_depth_causes": {},
    }  # fmt: skip
    counted = [m.target_causes for m in per_frame if m.target_causes]
    if counted and n_target:
        total = np.sum(counted, axis=0)
        out["no_depth_causes"] = {CAUSE_NAMES[c]: float(total[c] / n_target)
                                  for c in range(1, len(total)) if total[c]}  # fmt: skip
    return out


# ----------------------------------------------------------------------------- recordings


def truth_dir(rec_path: str | Path) -> Path:
    """``REC/ground_truth`` of a recording folder (or of its ``recording.json``)."""
    root = Path(rec_path)
    if root.name == "recording.json":
        root = root.parent
    return root / TRUTH_DIR


def require_truth(rec_path: str | Path) -> Path:
    """The ground-truth folder of a recording; ConfigError (one line) when it has none."""
    d = truth_dir(rec_path)
    if not d.is_dir():
        raise ConfigError(
            f"{rec_path}: no ground truth ({TRUTH_DIR}/ folder) — eval needs a simulated recording"
        )
    return d


def read_scene_info(rec_path: str | Path) -> dict:
    """``ground_truth/scene.json`` of a simulated recording ({} when absent)."""
    from lightflow.app.core.rig import read_json

    path = truth_dir(rec_path) / SCENE_JSON
    if not path.is_file():
        return {}
    data = read_json(path)
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a JSON object")
    return data


def evaluate_recording(
    rec_path: str | Path,
    rig: Rig | None = None,
    config=None,
    progress: Callable[[str, int, int], None] | None = None,
    stages: bool = False,
    picture: str | Path | None = None,
    title: str = "",
) -> RecordingMetrics:
    """Replay every frame of a simulated recording through the pipeline and score it.

    Parameters
    ----------
    rec_path : str or Path
        Recording folder written by ``lightflow simulate``.
    rig : Rig, optional
        Overrides the embedded rig.
    config : PipelineConfig, optional
    progress : callable, optional
        ``progress(stage, done, total)`` with stage ``"depth table"`` (LUT build)
        and ``"frames"``.
    stages : bool
        Also attribute the error to the stages (:mod:`lightflow.app.stages`),
        against the true flows in ``ground_truth/<frame>_flows.npz`` or, without
        them, computed from the built-in scene.
    picture : str or Path, optional
        Also draw the last frame's camera image, depth error and causes of no depth
        into this PNG (:func:`lightflow.app.pictures.case_picture`).
    title : str
        The picture's heading before its figures (default: the recording's folder).

    Raises
    ------
    ConfigError
        When the recording has no ground truth or a frame's ground truth is
        missing or of the wrong size.
    """
    from lightflow.app.core.geometry import camera_rays
    from lightflow.app.core.pipeline import DepthPipeline, PipelineConfig
    from lightflow.app.recording import load_frame, read_recording
    from lightflow.drivers.base import Frame
    from lightflow.drivers.sim.synthetic import GroundTruth

    rec = read_recording(rec_path, rig)
    tdir = require_truth(rec_path)
    info = read_scene_info(rec_path)
    config = config or PipelineConfig()
    lut_progress = (lambda i, n: progress("depth table", i, n)) if progress else None
    pipeline = DepthPipeline(rec.rig, config, progress=lut_progress)
    rays = camera_rays(rec.rig.camera)
    n_proj = len(rec.rig.projectors)
    # one projector with static depth measures the static background too: not off the object
    still = pipeline.flow_model.still_depth(config.flow)
    per_frame = []
    stage_frames = []
    renderer = None
    planar = bool(info.get("planar", False))
    for i, entry in enumerate(rec.frames):
        tpath = tdir / f"{entry.stem}.npz"
        if not tpath.is_file():
            raise ConfigError(f"{tpath}: ground truth of frames[{i}] ({entry.file}) missing")
        truth = GroundTruth.load(tpath)
        cam = rec.rig.camera
        if truth.depth.shape != (cam.height, cam.width):
            h, w = truth.depth.shape
            raise ConfigError(
                f"{tpath}: depth: {w}x{h}, expected {cam.width}x{cam.height} (the rig's camera)"
            )
        planar = planar or truth.planar
        frame = Frame(i, entry.t, rec.exposure_s, load_frame(rec, i), entry.stem)
        following = None
        if i == 0 and len(rec.frames) > 1:
            # as a replay does: the first frame's lines compared with the next frame's
            e1 = rec.frames[1]
            following = Frame(1, e1.t, rec.exposure_s, load_frame(rec, 1), e1.stem)
        result = pipeline.process(frame, following)
        per_frame.append(evaluate_frame(result.depth, truth, rays, n_proj, result.depth_std,
                                        result.causes_grid, result.stride,
                                        background=still))  # fmt: skip
        if stages:
            from lightflow.app import stages as st

            fpath = tdir / f"{entry.stem}{st.FLOWS_SUFFIX}"
            if fpath.is_file():
                flows = st.TrueFlows.load(fpath)
            else:
                if renderer is None:
                    from lightflow.drivers.sim.scenes import get_scene
                    from lightflow.drivers.sim.synthetic import SceneRenderer

                    renderer = SceneRenderer(rec.rig, get_scene(str(info.get("scene", "?"))))
                flows = st.true_flows(renderer, entry.t, rec.exposure_s)
            stage_frames.append(st.stage_errors(
                result.flows_grid, result.log_ratio_grid, result.depth, truth, flows,
                result.stride, rec.rig.single_projector, result.causes_grid,
                result.intervals_grid))  # fmt: skip
        if progress:
            progress("frames", i + 1, len(rec.frames))
    if picture is not None and per_frame:
        from lightflow.app.pictures import case_picture

        last = per_frame[-1]
        case_picture(
            frame.image, result.depth, truth, _target_mask(truth, n_proj), result.causes_grid,
            result.stride, f"{title or Path(rec_path).name}, frame {len(per_frame) - 1}: median "
            f"{1e3 * last.median_error_m:.1f} mm, signed {1e3 * last.median_signed_m:+.1f} mm, "
            f"coverage {100 * last.coverage:.0f} %", picture,
        )  # fmt: skip
    return RecordingMetrics(
        path=str(rec_path),
        scene=str(info.get("scene", "?")),
        exposure_s=rec.exposure_s,
        frames=len(per_frame),
        stride=config.stride,
        planar=planar,
        per_frame=tuple(per_frame),
        stages=_stage_summary(stage_frames),
        **pool_metrics(per_frame),
    )


def _stage_summary(stage_frames: list[dict]) -> dict:
    if not stage_frames:
        return {}
    from lightflow.app.stages import summarise

    return summarise(stage_frames)


def write_metrics_json(metrics: list[RecordingMetrics], path: str | Path) -> None:
    """Dump recording metrics (with per-frame figures) as JSON."""
    doc = {"format": "lightflow-eval/1", "recordings": [m.to_dict() for m in metrics]}
    Path(path).write_text(json.dumps(doc, indent=1) + "\n")
