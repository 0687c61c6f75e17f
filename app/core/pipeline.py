"""The per-frame depth pipeline: unmix, bands, flows, ratio, smoothing, LUT, depth.

:class:`DepthPipeline` is pure computation on one thread (no hardware, no
Rerun); :mod:`lightflow.app.runner` puts it between a camera and the sinks.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field, fields, replace

import cv2
import numba as nb
import numpy as np

from . import arcs, snapping, triangulation
from . import bands as bd
from . import causes as cz
from . import intervals as iv
from . import overlap as ov
from . import response as rsp
from .arcs import ArcIntervals
from .depth_model import (
    DepthLUT,
    DepthRange,
    depth_and_slope,
    load_or_build_lut,
    lookup_depth,
    update_depth_and_slope,
)
from .errors import ConfigError, FrameError
from .flow import (
    STILL_LINE_FRAMES,
    FlowModel,
    FlowParams,
    moved_lines,
    smooth_log_ratio,
    still_lines,
    warm_up_reread,
)
from .intervals import IntervalModel
from .kernel_options import NO_CFUNC
from .profile_model import static_width_excess, tables
from .results import BandSet, FrameResult
from .rig import CHANNEL_INDEX, Rig
from .snapping import LineSnapping, column_direction, desnap_intervals
from .threads import run_rows, run_tasks
from .triangulation import LineTriangulation

MAX_BANDS_PER_ROW = 160
#: print as long as a photo block is filled (``bands.print_block_px``) only in tiles of
#: this many pixels where the lines stand upright
BLOCK_TILE_PX = 128
#: ... and where the short fill changed this share of the pixels (print is near): text
#: 16-46 % of a tile on the tuning rigs' newspaper, a fan's blade edges 0-8 %, boards and
#: balls 0-5 %
BLOCK_PRINT_SHARE = 0.1
#: the local spread of the sweeps over-counts independent bands (neighbouring rows see
#: the same surface through the same blur): the random part of the predicted error is
#: scaled by this (chosen on the tuning rigs of the evaluation matrix)
NOISE_SCALE = 2.0
#: error of the log flow ratio that no local spread shows (profile model, pattern
#: geometry), one sigma (tuning rigs; the same for one and two projectors)
LOG_RATIO_FLOOR = 0.01
#: overlapping bands: a run is measured when the predicted error of its sweep is within
#: this share of it (tuning rigs)
OVERLAP_MAX_REL_STD = 0.02
#: the share of the grid's cells that must want a depth from the intervals for the
#: pass to run (about 6 ms of CPU at 1600x1200, for any number of cells): a board's
#: few scattered uncertain cells (0.03 %) are not worth it, a fan's hub is (5-10 %)
MIN_SLOW_SHARE = 0.0025
#: lines that moved since the last frame mark a moving surface only within this many grid
#: cells of a depth the last frame measured: a ball's lines moving along themselves move
#: on a surface measured there before, whereas where a fan's blade came or went the hub's
#: or the wall's lines changed under it (with frames not locked to the blades, the tuning
#: fans had 4 % of their depth on hub and wall; 0 cells cost two development balls 2-10
#: points, 2 cells 1-5, 4 cells 0-2)
MOVED_NEAR_DEPTH_CELLS = 4
#: the first frame, compared with the next one (``process(frame, following)``): lines that
#: moved mark a moving surface only within its own depth or enclosed by it, over gaps of up
#: to twice this many grid cells (a ball's slow middle; not the wall ahead of a blade,
#: where the next frame's blade came: within 4 cells of the depth the fans had 0.3-7.5
#: points more depth off the blades on 3 of 4 tuning and fresh rigs; enclosed over 2
#: cells, tuning, development and fresh balls +0.1 to +5.3 points of coverage, fans within
#: +0.05 points off the blades; over 3 cells, balls +0.1 to +6.7, fans up to +0.16)
ENCLOSE_GAP_CELLS = 2
#: depth from the line intervals (two projectors): random error of one band's log
#: interval ratio, and the error no averaging removes (line centres biased by blur and
#: sweep, the tables' geometry, a curved surface), one sigma (tuning rigs: the intervals
#: on boards and fans against the renderer's truth; the floor 0.005 -> 0.01 took the
#: share of fan and ball errors within 1 sigma from 28-60 % to 46-66 %, depths unchanged)
INTERVAL_NOISE = 0.007
INTERVAL_FLOOR = 0.01


@dataclass(frozen=True)
class PipelineConfig:
    """Options of the depth pipeline.

    Attributes
    ----------
    stride : int
        Analysis grid stride: bands are measured on every ``stride``-th row and
        flows/depth computed on every ``stride``-th column, then depth is
        interpolated back to full resolution.  1, 2, 4 (the default) or 8, which
        takes about half the CPU of 4 for the same accuracy and 1-5 points less
        coverage on the tuning matrix (-5 to +3 held out; more on objects small in the
        image).
    depth_range : DepthRange
    flow : FlowParams
    bands : BandParams
    crosstalk : str or float
        ``auto`` takes the colour leak from the rig (each pattern's ``crosstalk``,
        measured by ``lightflow rig blur``), else estimates it from the frames now and
        then; a number fixes it.
    crosstalk_every : int
        Frames between two estimates of the colour leak (and of the band windows).
    max_depth_std : float
        Pixels whose predicted depth standard deviation exceeds this share of
        their depth get none (cause ``uncertain``).
    arc_intervals : bool
        Two projectors with uniform patterns: each band's line interval from the
        circular arc through its line and its two neighbours, placed at the first
        pass's depth, instead of the mean spacing (:mod:`lightflow.app.core.arcs`).
    arc_recheck : bool
        With ``arc_intervals``: where a limb or steep band's arc was placed at a depth
        the frame then does not measure at the band (:meth:`ArcIntervals.recheck`), the
        arcs are placed again there and the flows read again.  Off by default: on the
        development rigs' two balls it gains up to 12 points of coverage, but held out
        it gained 0-3.5 points and raised the share of gross errors on 6 of 8 cases it
        changed; it costs 15-30 ms per 1600x1200 frame of a ball or fan (nothing on
        boards, whose frames have no such bands).
    predict_intervals : bool
        Two projectors: where the sparse pattern's measured line interval
        disagrees with the one its dense partner and the rig predict (curved
        surfaces), use the prediction (:mod:`lightflow.app.core.intervals`).
    interval_depth : bool
        Two projectors: cells whose lines move, but too little for a flow (a fan
        near its hub at 1 ms), get the depth their two line intervals give
        (:meth:`~lightflow.app.core.intervals.IntervalModel.depth`; needs
        ``predict_intervals``).  Lines that stand still (a wall) get none.
    triangulate : bool
        Give each band the depth of its line's plane on its camera ray, the line found
        where both patterns' depths agree (the flow's depth names the candidates), and
        the moving cells between such bands their depth
        (:mod:`lightflow.app.core.triangulation`).
    measure_overlap : bool
        Measure the sweeps of runs of overlapping bands (rejected by the band
        detector) on their periodic profile (:func:`~lightflow.app.core.overlap.measure_runs`;
        rigs with uniform patterns).
    whole_columns : bool
        The projected lines sit on whole projector columns, so a uniform pattern's
        spacings alternate between the two whole numbers around the pitch, and an
        exp2 pattern's are 1-5 % off; take that out of each band's interval
        (:mod:`lightflow.app.core.snapping`).
    camera_gamma : float or "auto", optional
        The camera's response, ``DN = full * (light / full) ** (1 / gamma)``;
        default: the rig's (``camera.gamma``; 1, linear, when it gives none).  Unless it
        is 1, every frame is linearised first (:mod:`lightflow.app.core.response`).
        ``auto``: measured on the lines that stand still between the first frames (a
        wall), when the rig gives none.  Not the default: on the demo's half-size wall
        a linear camera measured 0.89 (its thin lines are too blurred to tell).
    """

    stride: int = 4
    depth_range: DepthRange = field(default_factory=DepthRange)
    flow: FlowParams = field(default_factory=FlowParams)
    bands: bd.BandParams = field(default_factory=bd.BandParams)
    crosstalk: str | float = "auto"
    crosstalk_every: int = 30
    # chosen on the tuning rigs with their measured blur: 0.03 -> 0.05 took the fan and the
    # balls from 14-34 % to 28-48 % coverage, medians within 3 mm (0.08 added little more)
    max_depth_std: float = 0.05
    arc_intervals: bool = True
    arc_recheck: bool = False
    predict_intervals: bool = True
    interval_depth: bool = True
    triangulate: bool = True
    measure_overlap: bool = True
    whole_columns: bool = True
    camera_gamma: float | str | None = None

    def __post_init__(self):
        if self.stride not in (1, 2, 4, 8):
            raise ConfigError(f"stride: expected 1, 2, 4 or 8, got {self.stride}")
        lo, hi = rsp.GAMMA_RANGE
        if self.camera_gamma not in (None, "auto") and not lo <= self.camera_gamma <= hi:
            raise ConfigError(f"camera_gamma: expected {lo:g} to {hi:g} (1: a linear camera), "
                              f"got {self.camera_gamma}")  # fmt: skip
        if not self.max_depth_std > 0:
            raise ConfigError(f"max_depth_std: expected a positive share of the depth, "
                              f"got {self.max_depth_std}")  # fmt: skip

    @staticmethod
    def from_dict(d: dict, source: str = "pipeline options") -> PipelineConfig:
        """Build from a flat dict, rejecting unknown keys."""
        known = {f.name for f in fields(PipelineConfig)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ConfigError(f"{source}: unknown option {unknown[0]!r}")
        return PipelineConfig(**d)


class DepthPipeline:
    """Turns camera frames into depth for one rig.

    Parameters
    ----------
    rig : Rig
    config : PipelineConfig
    lut : DepthLUT, optional
        Precomputed LUT; loaded from the cache or built when omitted.
    progress : callable, optional
        ``progress(done, total)`` while the LUT is built.
    """

    def __init__(
        self,
        rig: Rig,
        config: PipelineConfig | None = None,
        lut: DepthLUT | None = None,
        progress=None,
    ):
        self.rig = rig
        self.config = config or PipelineConfig()
        cfg = self.config
        if cfg.flow.static_depth == "on" and not rig.single_projector:
            raise ConfigError(f"{rig.source}: static_depth 'on' needs a single projector (exp2 "
                              f"pair); with two projectors the depth is in the motion")  # fmt: skip
        self.lut = lut or load_or_build_lut(rig, cfg.stride, cfg.depth_range, progress)
        if self.lut.stride != cfg.stride:
            raise ConfigError(f"LUT stride {self.lut.stride} differs from stride {cfg.stride}")
        usable = float(np.mean(self.lut.usable))
        if usable < 0.05:
            raise ConfigError(
                f"{rig.source}: projectors: the flow ratio does not change with depth on "
                f"{100 * (1 - usable):.0f} % of the image (parallel projectors, or a single "
                f"projector with like patterns?): no depth can be measured; "
                f"see `lightflow rig check`"
            )
        self.flow_model = FlowModel(rig)
        self.intervals = None
        if cfg.predict_intervals and not rig.single_projector:
            self.intervals = IntervalModel(rig, cfg.stride, cfg.depth_range)
        self.flow_model.stride = cfg.stride
        #: the overlap measurement's tuning, None when it is off (or the patterns are not
        #: uniform: their line width in camera px needs the local pitch)
        self._overlap = None
        if cfg.measure_overlap and np.all(self.flow_model.kinds == 0):
            self._overlap = ov.OverlapParams(max_rel_std=OVERLAP_MAX_REL_STD)
        #: the last measured frame's cells whose sweeps come from overlapping bands
        #: (``(2, h, w)`` bool), None when there are none
        self._periodic: np.ndarray | None = None
        self.channels = [CHANNEL_INDEX[pat.channel] for _, pat in rig.patterns]
        cam = rig.camera
        self.grid_shape = self.lut.h0.shape
        self._leak = np.zeros(2)
        self._leak_known = np.zeros(2, dtype=bool)
        # a crosstalk measured on still lines (``lightflow rig blur``) is the rig's own: the
        # frames' estimates need clean gaps between bands, which long sweeps do not leave
        self._rig_leak = rig.crosstalk if cfg.crosstalk == "auto" else None
        if self._rig_leak is not None:
            self._leak[:] = self._rig_leak
            self._leak_known[:] = True
        self._windows: np.ndarray | None = None
        self._frames = 0
        self.blur_px: list[float] = [np.nan, np.nan]
        b = cfg.bands
        self._band_params = np.array(
            [b.min_contrast, b.interval_tolerance, b.symmetry_tolerance_px, b.min_gap_px,
             b.vertical_extra],
            dtype=np.float64,
        )  # fmt: skip
        self._fields = np.array(bd.GRID_FIELDS, dtype=np.int64)
        # per pattern: where its lines really sit (None: on whole columns, or not asked for)
        middle = float(np.sqrt(cfg.depth_range.near * cfg.depth_range.far))
        self._snapping = [
            LineSnapping.of(pat, proj.width, column_direction(rig.camera, proj, middle),
                            MAX_BANDS_PER_ROW) if cfg.whole_columns else None
            for proj, pat in rig.patterns
        ]  # fmt: skip
        # measured image rows: rows_per_cell rows around the centre of every grid cell
        s = cfg.stride
        k = max(1, min(b.rows_per_cell, s))
        first = (s - k) // 2
        gh = self.grid_shape[0]
        self._rows_per_cell = k
        self._row_y = (np.arange(gh)[:, None] * s + first + np.arange(k)[None, :]).ravel()
        self._arcs = None
        if cfg.arc_intervals and not rig.single_projector and np.all(self.flow_model.kinds == 0):
            self._arcs = ArcIntervals(rig, self._row_y, middle)
        self._triangulation = (LineTriangulation(rig, self._row_y, cfg.depth_range)
                               if cfg.triangulate else None)  # fmt: skip
        # ... and the rows averaged around them
        extra = np.arange(-b.vertical_extra, b.vertical_extra + 1)
        self._read_rows = np.unique(np.clip(self._row_y[:, None] + extra, 0, cam.height - 1))
        # per-frame scratch (about 10 MB), reused: results only keep copies out of it
        self._buffers = (
            np.empty((2, len(self._row_y), MAX_BANDS_PER_ROW, bd.N_FIELDS)),
            np.empty((2, len(self._row_y)), np.int64),
        )
        #: per band, its centre had its lines been at their nominal columns (snapping)
        self._nominal = np.full(self._buffers[1].shape + (MAX_BANDS_PER_ROW,), np.nan)
        self._full_size = (cam.width, cam.height)
        self._full_scale = 255.0
        #: the camera's response (1: linear), and the table that undoes it for the
        #: last frame's type
        given = cfg.camera_gamma not in (None, "auto")
        self.camera_gamma = (cfg.camera_gamma if given else rig.camera.gamma) or 1.0
        #: where the response came from: "option", "rig", "still lines", "linear" (taken as
        #: 1) or "" (``auto``: to be measured on still lines, 1 until then)
        self.gamma_source = ("option" if given else "rig" if rig.camera.gamma is not None
                             else "" if cfg.camera_gamma == "auto" else "linear")  # fmt: skip
        #: the measurement on still lines before it was rounded to 1 (NaN: none)
        self.gamma_measured = float("nan")
        self._linear_table: tuple | None = None
        # neither option nor rig gives the response: measured on the lines that stand
        # still between the first frames (a wall), as the blur is; the frame before
        self._gamma_prev: tuple | None = None
        #: the last frame's band widths and line intervals ``(2, 2, h, w)``: lines that
        #: moved since are on a moving surface, even where they stand still within the
        #: exposure (None before the first frame)
        self._previous_lines: np.ndarray | None = None
        #: the last frame's depth grid (None before the first frame)
        self._previous_depth: np.ndarray | None = None

    # ------------------------------------------------------------------ stages

    def _weights(self, image: np.ndarray) -> np.ndarray:
        """Per pattern, RGB weights that isolate its channel (crosstalk removed)."""
        a, b = self.channels
        cfg = self.config
        if cfg.crosstalk != "auto":
            self._leak[:] = float(cfg.crosstalk)
        elif self._rig_leak is None and self._frames % cfg.crosstalk_every == 0:
            # a property of the rig, not of a frame: refresh now and then, smoothed
            est = self._crosstalk_in(image)
            # a frame without clean gaps keeps the last estimate (0 until there is one)
            fresh = np.isfinite(est)
            blended = np.where(self._leak_known, 0.7 * self._leak + 0.3 * est, est)
            self._leak = np.where(fresh, blended, self._leak)
            self._leak_known |= fresh
        w = np.zeros((2, 3))
        w[0, a], w[0, b] = 1.0, -self._leak[0]
        w[1, b], w[1, a] = 1.0, -self._leak[1]
        return w

    def _detect(self, image, weights, row_y, wins, group=1, out=None):
        if out is None:
            bands = np.empty((2, len(row_y), MAX_BANDS_PER_ROW, bd.N_FIELDS))
            counts = np.empty((2, len(row_y)), np.int64)
        else:
            bands, counts = out
        bd.detect_bands(image, weights, row_y, wins, self._full_scale, self._band_params,
                        self.flow_model.edge_model(), bands, counts, group)  # fmt: skip
        return bands, counts

    @staticmethod
    def _learning_rows(height: int) -> np.ndarray:
        """The image rows :meth:`_learn_windows` measures."""
        step = max(8, height // 48)
        return np.arange(step // 2, height, step, dtype=np.int64)

    def _learn_windows(self, image, weights) -> np.ndarray:
        """Sliding window of the band detector: about two line intervals, learnt per pattern."""
        wide = max(31, image.shape[1] // 12) | 1
        row_y = self._learning_rows(image.shape[0])
        bands, counts = self._detect(image, weights, row_y, np.array([wide, wide]))
        wins = np.full(2, wide, np.int64)
        for p in range(2):
            iv = np.concatenate([bands[p, r, : counts[p, r], bd.F_INTERVAL]
                                 for r in range(counts.shape[1])])  # fmt: skip
            iv = iv[np.isfinite(iv)]
            if iv.size >= 10:
                wins[p] = int(2 * np.median(iv)) | 1
        return wins

    # ------------------------------------------------------------------ public

    def warm_up(self, optional: bool = True) -> float:
        """Compile the kernels and load the tables before a camera streams; return seconds.

        The first frame through a fresh process costs hundreds of milliseconds
        (numba compilation, table loading); done while a camera streams, that
        stall would back up into the camera.  A scratch pipeline sharing this
        one's depth table processes a striped test image, so this pipeline's
        learnt state (colour leak, windows) still starts from real frames.
        ``optional=False`` leaves out :meth:`warm_up_optional` (for a caller that has
        another process compile those kernels meanwhile).
        """
        from types import SimpleNamespace

        t0 = time.perf_counter()
        cam = self.rig.camera
        x = np.arange(cam.width)
        image = np.full((cam.height, cam.width, 3), 20, np.uint8)
        image[:, (x % 40) < 14, 0] = 200  # red lines, a 40 px interval
        image[:, (x % 18) < 7, 2] = 200  # blue lines, an 18 px interval
        # the arcs' and the triangulation's kernels are optional here: a demo's helper
        # process compiles them
        config = self.config if optional else replace(self.config, arc_intervals=False,
                                                      triangulate=False)  # fmt: skip
        scratch = DepthPipeline(self.rig, config, lut=self.lut)
        # process() needs only these of a Frame (the core does not import drivers)
        scratch.process(SimpleNamespace(image=image, stem="warm-up", full_scale=255.0))
        # the smoothing's outlier test needs 16 finite log ratios, which stripes do not give
        ramp = np.linspace(-0.1, 0.1, 64, dtype=np.float32).reshape(8, 8)
        smooth_log_ratio(ramp, 1.0, self.config.flow.outlier_sigmas,
                         self.config.flow.fill_fraction, ramp * ramp)  # fmt: skip
        # the blur fit and the still-line response read the tables through one more kernel,
        # on the first frames that refit them (a rig without a measured blur)
        tables().measured_width(np.zeros(1), np.ones(1), np.ones(1))
        if optional:
            self.warm_up_optional()
        if self.intervals is not None:
            # straight stripes bend nowhere, so the interval prediction ran on no cell:
            # compile it here, with the argument types of a frame (a grid field view)
            grids = np.full((2, len(self._fields), 4, 4), 20.0)
            grids[1, 1] = 45.0
            depth = np.full((4, 4), 0.7, np.float32)
            self.intervals.disagreement(grids[:, 1], np.where(depth > 0, depth, np.nan))
        return time.perf_counter() - t0

    def warm_up_optional(self) -> None:
        """Compile (or load) the kernels of the stages the test image of :meth:`warm_up`
        does not reach: overlapping bands, when they are measured (about 6 s of
        compilation on a first run, the largest part of the pipeline's), the depth
        from the line intervals (about 1.3 s; it runs only where lines move too little),
        the whole-column intervals (about 3.7 s; only for patterns whose lines are
        off their nominal centres), the arcs' intervals (about 3.5 s;
        :func:`lightflow.app.core.arcs.warm_up`), the triangulated depth
        (:func:`lightflow.app.core.triangulation.warm_up`) and the second reading of the
        flows and the interval depth's own kernels (about 2.5 s; :func:`warm_up_kernels`,
        :func:`lightflow.app.core.flow.warm_up_reread`).
        """
        if self._overlap is not None:
            ov.warm_up(self._overlap)
        if self.intervals is not None and self.config.interval_depth:
            iv.warm_up()
        if any(s is not None for s in self._snapping):
            snapping.warm_up()
        if self._arcs is not None:
            arcs.warm_up()
        if self._triangulation is not None:
            triangulation.warm_up()
        # the second reading and the interval depth: reached by no test image of stripes
        warm_up_reread()
        warm_up_kernels()

    #: attributes that are not cross-frame state: the rig, options, tables, scratch
    _CONSTANT = frozenset({"rig", "config", "lut", "flow_model", "intervals", "_buffers",
                           "_full_size", "_linear_table", "_overlap", "_periodic",
                           "_rig_leak", "_snapping", "_arcs", "_nominal"})  # fmt: skip
    _FLOW_CONSTANT = frozenset({"rig", "pairs"})

    def state(self) -> dict:
        """A picklable copy of everything carried from one frame to the next.

        Colour leak, learnt band windows, the blur model and its pool of bands,
        and the frame counters that schedule their updates.  With
        :meth:`restore`, a chunk of a recording can start where a sequential
        replay would be (``lightflow batch``).
        """
        import copy

        return {
            "pipeline": {k: copy.deepcopy(v) for k, v in vars(self).items()
                         if k not in self._CONSTANT},
            "flow": {k: copy.deepcopy(v) for k, v in vars(self.flow_model).items()
                     if k not in self._FLOW_CONSTANT},
        }  # fmt: skip

    def restore(self, state: dict, frames_done: int | None = None) -> None:
        """Continue from :meth:`state`; the next frame counts as frame ``frames_done``."""
        import copy

        for name, value in state["pipeline"].items():
            setattr(self, name, copy.deepcopy(value))
        for name, value in state["flow"].items():
            setattr(self.flow_model, name, copy.deepcopy(value))
        if frames_done is not None:
            self._frames = frames_done
            self.flow_model.frames = frames_done

    def updates_state_at(self, frame: int) -> bool:
        """Whether the ``frame``-th frame may change the cross-frame state.

        May say yes too often, never too rarely: the leak and windows are
        relearnt every ``crosstalk_every`` frames, the blur model on its own
        schedule (:meth:`FlowModel.refits_at`).
        """
        return (frame % self.config.crosstalk_every == 0
                or self.flow_model.refits_at(frame, self.config.flow)
                or (not self.gamma_source and frame <= STILL_LINE_FRAMES[-1]))  # fmt: skip

    def band_grids(self, frame) -> np.ndarray:
        """The band measurements of one frame on the analysis grid (no flow, no depth).

        Returns
        -------
        numpy.ndarray
            ``(2, 4, h, w)``: per pattern, the band width at half height, the line
            interval, the 50->20 % ramp (camera px) and the lines' slant (columns
            per row); NaN where no valid band is near.  What
            ``lightflow rig blur`` measures static lines with.
        """
        return self._measure(frame, {})[2]

    def process(self, frame, following=None) -> FrameResult:
        """Depth for one frame.  Never raises on image content: bad pixels are NaN.

        ``following``: the next frame, used for the first frame of a sequence only (a
        replay passes it).  Lines that stand still within an exposure can still belong
        to a moving surface (a ball's slow middle, its lines moving along themselves):
        between frames they move.  A later frame compares its lines with the frame
        before (:func:`~.flow.moved_lines`, near the depth that frame measured); the
        first has none before it, so it compares them with the next frame's, processed
        first without changing the pipeline's state (this frame costs about twice as
        much), and only inside its own moving surfaces (:data:`ENCLOSE_GAP_CELLS`).
        """
        ahead = following is not None and self._previous_lines is None and self._frames == 0
        timings = {}
        t_ahead = time.perf_counter()
        if ahead:
            # the next frame processed as if it came first, then the state put back: only
            # its lines and depth stay, as a frame before this one would leave them
            saved = self.state()
            self.process(following)
            lines, depth = self._previous_lines, self._previous_depth
            self.restore(saved)
            self._previous_lines, self._previous_depth = lines, depth
            # the first frame's time counts this too (its "total": the whole call)
            timings["next frame"] = (time.perf_counter() - t_ahead) * 1e3
        cfg = self.config
        t0 = time.perf_counter()
        bands, counts, grids = self._measure(frame, timings)
        if not self.gamma_source and self._frames <= STILL_LINE_FRAMES[-1]:
            again = self._response_from_still_lines(frame, grids, timings)
            if again is not None:
                bands, counts, grids = again
                # the last frame's lines were read with another response: not comparable
                self._previous_lines = None
        moved = None if self._previous_lines is None else moved_lines(grids, self._previous_lines)
        if moved is not None and self._previous_depth is not None:
            moved &= _near(self._previous_depth)
        self._previous_lines = grids[:, :2].copy()
        t2 = time.perf_counter()
        flows = functools.partial(self.flow_model.combine, grids, cfg.flow, self._periodic)
        curved = None
        if self.intervals is None:
            fm = flows()
        else:
            # where the surface bends needs only the intervals: found on a pool thread
            # while this one combines the flows
            curved, fm = run_tasks(functools.partial(self.intervals.curved, grids[:, 1]), flows)
        self.blur_px = fm.blur_px
        t3 = time.perf_counter()
        timings["flow"] = (t3 - t2) * 1e3
        # predicted error of each pixel's depth, and no depth where it is too large
        z_raw, dz_dh = depth_and_slope(self.lut, fm.log_ratio)
        recheck = self._arcs is not None and cfg.arc_recheck
        if recheck:
            # as they were before the arcs: read again from here if some arcs were placed off
            kept = (bands.copy(), grids.copy(), z_raw.copy(), dz_dh.copy(),
                    replace(fm, why=fm.why.copy()))  # fmt: skip
        fm = self._read_again(fm, bands, counts, grids, z_raw, dz_dh, z_raw, curved)
        depth = self._flows_depth(fm, z_raw, dz_dh, grids[:, 1], curved)
        if recheck:
            # once: a second time gained the tuning and development balls under a point more
            # (the first reading's depth is kept where no band is flagged: no cost there)
            again = self._arcs.recheck(kept[0], bands, counts, kept[2], depth[2],
                                       self._rows_per_cell, cfg.stride)  # fmt: skip
            if again is not None:
                bands[...] = kept[0]
                grids[...] = kept[1]
                z_raw, dz_dh = kept[2], kept[3]
                fm = self._read_again(kept[4], bands, counts, grids, z_raw, dz_dh, again, curved)
                depth = self._flows_depth(fm, z_raw, dz_dh, grids[:, 1], curved)
        raw, log_ratio, depth_grid, std_grid = depth
        why = fm.why
        intervals = grids[:, 1]
        t4 = time.perf_counter()
        timings["smooth"] = (t4 - t3) * 1e3
        if self._triangulation is not None:
            # the flows' depths name the lines; cells whose lines move, or that have a
            # depth, and the bands of their surfaces up to lines that stand still (within
            # the exposure, and since the last frame: a ball's lines moving along themselves
            # stand still within it)
            moving = fm.swept | np.isfinite(depth_grid)
            still = why == cz.STATIC
            if ahead:
                # the first frame: only inside its own moving surfaces (the flows' depth).
                # A blade's lines moved where the next frame's blade came: the wall ahead
                # of it, next to its depth
                moved &= _enclosed(depth_grid)
            if moved is not None:
                still &= ~moved
            self._triangulation.refine(bands, counts, self._rows_per_cell, cfg.stride,
                                       depth_grid, moving, depth_grid, std_grid,
                                       still=still)  # fmt: skip
        lone = cz.lone_cells(depth_grid)
        depth_grid[lone] = np.nan
        std_grid[lone] = np.nan
        self._previous_depth = depth_grid.copy()
        t5 = time.perf_counter()
        timings["depth"] = (t5 - t4) * 1e3
        causes = self._causes(bands, counts, grids, why, raw, log_ratio, depth_grid)
        causes[lone] = cz.LONE
        counts_by_cause = cz.count_causes(causes)
        timings["total"] = (time.perf_counter() - (t_ahead if ahead else t0)) * 1e3
        self._frames += 1
        result_bands = [
            _band_set(pat.channel, bands[p], counts[p], self._row_y)
            for p, (_, pat) in enumerate(self.rig.patterns)
        ]
        return FrameResult(
            frame=frame,
            depth_map=None,
            depth_grid=depth_grid,
            full_size=self._full_size,
            flows_grid=fm.flows,
            log_ratio_grid=log_ratio,
            bands=result_bands,
            stride=cfg.stride,
            timings_ms=timings,
            coverage=float(counts_by_cause[cz.DEPTH] / causes.size),
            depth_std_grid=std_grid,
            causes_grid=causes,
            cause_counts=counts_by_cause,
            leak_known=bool(cfg.crosstalk != "auto" or self._leak_known.all()),
            warnings=self._warnings(counts_by_cause),
            intervals_grid=intervals,
        )

    def _read_again(self, fm, bands, counts, grids, z_raw, dz_dh, arc_depth, curved):
        """The flows read again with the arcs' and the surface's intervals: the new
        :class:`FlowMaps` (``fm`` itself where nothing changed).

        ``bands``, ``grids``, ``z_raw`` and ``dz_dh`` are changed in place (the depth
        and slope where the flows are read again); ``arc_depth``: the depth the arcs are
        placed at (:meth:`ArcIntervals.correct`).
        """
        cfg = self.config
        # a flow is L / B, and a sweep shorter than the line is read against the line's
        # width, B over the pitch: where the intervals are corrected, the sweeps are read
        # again with them
        added = fallback = None
        if self._arcs is not None:
            # the bands' intervals from the arcs through their lines, at this depth
            added, fallback = self._arc_intervals(bands, counts, arc_depth, grids)
        fix = np.zeros(grids[:, 1].shape, np.float32)
        if self.intervals is not None:
            fix = self.intervals.correct(grids[:, 1], z_raw, curved)
        if fix.any() or added is not None:
            first = fm
            fm = self.flow_model.reread(fm, grids, fix, cfg.flow, self._periodic, added,
                                        None if fallback is None else fallback + fix)  # fmt: skip
            # the second reading changes the log ratio near the cells read again only
            update_depth_and_slope(self.lut, fm.log_ratio, first.log_ratio, z_raw, dz_dh)
        return fm

    def _flows_depth(self, fm, z_raw, dz_dh, intervals, curved):
        """The flows' depth of a frame: ``(raw, log_ratio, depth_grid, std_grid)``, the log
        ratio screened (out of range or too uncertain: NaN), smoothed, its depth and the
        depth's predicted error, with the line intervals' depth where lines move too little
        for a flow (:meth:`_depth_from_intervals`).  ``fm.why`` is updated in place
        (:meth:`FlowMaps.screen`); ``fm`` is not otherwise changed."""
        cfg = self.config
        sigma_f = cfg.flow.smoothing_px / cfg.stride
        sigma_s = cfg.flow.sweep_smoothing_px / cfg.stride
        # the final smoothing averages the random part further (by its kernel area)
        gain = min(1.0, (sigma_s / sigma_f) ** 2) if sigma_f > 0 else 1.0
        # out of range or too uncertain: no depth
        raw, depth_var = fm.screen(z_raw, dz_dh, NOISE_SCALE**2 * gain, LOG_RATIO_FLOOR**2,
                                   cfg.max_depth_std)  # fmt: skip
        # the predicted variance is smoothed with the log ratio, over the same pixels
        log_ratio, var_grid = smooth_log_ratio(
            raw, sigma_f, cfg.flow.outlier_sigmas, cfg.flow.fill_fraction, depth_var,
        )  # fmt: skip
        std_grid = np.sqrt(var_grid)
        depth_grid = lookup_depth(self.lut, log_ratio)
        std_grid[~np.isfinite(depth_grid)] = np.nan
        if self.intervals is not None and cfg.interval_depth:
            slow = fm.swept & ((fm.why == cz.STATIC) | (fm.why == cz.UNCERTAIN))
            self._depth_from_intervals(intervals, fm.swept, slow, curved, sigma_f, depth_grid,
                                       std_grid)  # fmt: skip
        return raw, log_ratio, depth_grid, std_grid

    def _arc_intervals(self, bands, counts, depth, grids):
        """:class:`ArcIntervals` on the bands, and the rows of ``grids`` they change measured
        again (both in place).

        Returns ``(added, shift)``: per cell, whether it is to be read again (its interval
        changed, or its other fields: a limb or steep band became valid nearby), and per pattern
        ``log(old / new)`` of its interval (0 where it did not change); None and None when
        no band changed.
        """
        cfg = self.config
        changed, rescued, rows = self._arcs.correct(
            bands, counts, self._nominal, depth, self._rows_per_cell, cfg.stride,
            cfg.bands.interval_tolerance)
        if not (changed or rescued):
            return None, None
        gh, gw = self.grid_shape
        # the rows as they were: their intervals, and with rescued bands the other fields
        old = grids[:, :grids.shape[1] if rescued else 2].take(rows, axis=2)  # C order
        for p in range(2):
            bd.rasterise_cells(bands[p], counts[p], self._rows_per_cell, cfg.stride, gw, 0.5,
                               self._fields, grids[p], rows)  # fmt: skip
        ratio = np.empty((2, len(rows), gw))
        changed = np.empty((len(rows), gw), np.bool_)
        _compare_rows(old, grids, rows, ratio, changed)
        with np.errstate(invalid="ignore", divide="ignore"):
            np.log(ratio, out=ratio)  # numpy's log (the kernels' would round otherwise)
        shift = np.zeros((2, gh, gw), np.float32)
        added = np.zeros((gh, gw), bool)
        _shift_rows(ratio, rows, changed, shift, added)
        return added, shift

    def _depth_from_intervals(self, intervals, swept, slow, curved, sigma, depth_grid,
                              std_grid) -> None:  # fmt: skip
        """Fill ``depth_grid`` and ``std_grid`` (in place) where lines move too little for a
        flow, and average it with the flow's depth where the surface does not bend.

        ``swept``: the cells whose lines move (both patterns' bands wider than a still
        line); ``slow``: those of them that move too little for a flow (cause static or
        uncertain).  The depth the two line intervals give (:meth:`IntervalModel.depth`)
        is smoothed over the swept cells like the log flow ratio (the cells with a flow
        too: against them the outliers show), and kept where it is predicted within
        ``max_depth_std``.  Where a cell has both depths, they are averaged by their
        predicted precision, unless the surface bends there (``curved``, from
        :meth:`IntervalModel.curved`): a ball's measured intervals are biased, its
        interval depth with them.
        """
        if np.count_nonzero(slow & ~np.isfinite(depth_grid)) < MIN_SLOW_SHARE * slow.size:
            return  # a board: a few scattered cells are not worth a pass over the frame
        wanted = swept & ~np.isfinite(depth_grid)
        # the cells to fill and those the smoothing averages them with
        r = int(2.0 * sigma) + 1
        near = cv2.dilate(wanted.view(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8))
        z, sens = self.intervals.depth(intervals, swept & near.view(bool))
        if not np.isfinite(z).any():
            return
        # independent bands under the kernel: cells times the stride over the interval
        cells = 4.0 * np.pi * sigma * sigma * self.config.stride
        var = np.empty(z.shape, np.float32)
        run_rows(_interval_variance, var.shape[0], intervals, sens, cells, INTERVAL_NOISE**2,
                 INTERVAL_FLOOR**2, var)  # fmt: skip
        with np.errstate(invalid="ignore", divide="ignore"):
            log_z = np.log(z)  # numpy's log (a kernel's would round otherwise)
        log_z, var = smooth_log_ratio(log_z, sigma, self.config.flow.outlier_sigmas,
                                      self.config.flow.fill_fraction, var)  # fmt: skip
        z = np.exp(log_z)
        limits = (self.config.max_depth_std, self.config.depth_range.near,
                  self.config.depth_range.far)  # fmt: skip
        run_rows(_join_interval_depth, z.shape[0], z, var, swept, curved,
                 *(np.float32(v) for v in limits), depth_grid, std_grid)  # fmt: skip

    def _measure(self, frame, timings: dict, buffers=None):
        """Unmix and measure the bands of ``frame``: ``(bands, counts, grids)``.

        ``bands`` and ``counts`` are views of ``buffers`` (default: the pipeline's
        scratch, overwritten by the next call).
        """
        cfg = self.config
        t0 = time.perf_counter()
        image = self._prepared(frame)
        weights = self._weights(image)
        relearn = self._windows is None or self._frames % cfg.crosstalk_every == 0
        rows = self._read_rows
        if relearn:
            rows = np.union1d(rows, self._learning_rows(image.shape[0]))
        # only the rows the detector reads
        raw = image
        image = bd.fill_print(image, cfg.bands.print_fill_px,
                              cfg.bands.min_contrast * self._full_scale, rows)  # fmt: skip
        if relearn:
            # relearnt now and then: the first frame may have had merged or no bands
            self._windows = self._learn_windows(image, weights)
        t1 = time.perf_counter()
        timings["unmix"] = (t1 - t0) * 1e3
        gh, gw = self.grid_shape
        bands, counts = self._detect(
            image, weights, self._row_y, self._windows, self._rows_per_cell,
            self._buffers if buffers is None else buffers,
        )  # fmt: skip
        image = self._fill_blocks(raw, image, weights, bands, counts)
        t2 = time.perf_counter()
        timings["bands"] = (t2 - t1) * 1e3
        k = self._rows_per_cell
        self._periodic = None
        if self._overlap is not None:
            fm = self.flow_model
            # bands valid alone read right where the detector knew line width and blur
            known = bool(np.all(fm.edge_model()[:, 0] > 0.0))
            if ov.measure_runs(image, weights, self._row_y, bands, counts, fm.line_px, fm.steps,
                               fm.blur, self._overlap, tight_runs=not known):  # fmt: skip
                # cells nearer a periodic band than a band measured alone (codes 2, 1)
                codes = np.empty((2, 2, gh, gw))
                fields = np.array([bd.F_VALID, bd.F_INTERVAL], np.int64)
                for p in range(2):
                    bd.rasterise_cells(bands[p], counts[p], k, cfg.stride, gw, 0.5, fields,
                                       codes[p])  # fmt: skip
                self._periodic = codes[:, 0] > 0.5 * (bd.BAND_VALID + bd.BAND_PERIODIC)
        t3 = time.perf_counter()
        timings["overlap"] = (t3 - t2) * 1e3
        for p in range(2):
            bd.band_slants(bands[p], counts[p], self._row_y)
        # the pipeline's own scratch holds the frame's bands: so does its nominal centres'
        nominal = self._nominal if buffers is None else np.empty(counts.shape + bands.shape[2:3])
        nominal[:] = np.nan
        # the two patterns on two threads (the kernel releases the GIL)
        run_tasks(*(functools.partial(desnap_intervals, bands[p], counts[p], snap, nominal[p])
                    for p, snap in enumerate(self._snapping) if snap is not None))  # fmt: skip
        grids = np.empty((2, len(self._fields), gh, gw))
        for p in range(2):
            bd.rasterise_cells(bands[p], counts[p], k, cfg.stride, gw, 0.5, self._fields, grids[p])
        timings["bands"] += (time.perf_counter() - t3) * 1e3
        return bands, counts, grids

    def _fill_blocks(self, raw, image, weights, bands, counts):
        """Fill print as long as a photo block where there is print and lines stand upright,
        and measure those rows again.

        The short fill (``print_fill_px``) is safe for any line.  A segment as long as
        ``print_block_px`` is not: along a slanted line it crosses the gaps between its
        bands, and beside a depth edge (a fan's blade) it joins the lines of two
        surfaces.  So the long one is used only in tiles where the short fill found
        print (:data:`BLOCK_PRINT_SHARE` of their pixels) and whose valid bands stand
        upright (:func:`~lightflow.app.core.bands.upright_tiles`), only on the grid
        cells where such a tile holds bands that were cut, irregular or overlapping,
        and only where the dip keeps some light (a dip to the unlit level is a gap) and
        the segment lies within the image.  The rows it changed are overwritten in
        ``image`` (``raw`` filled short: its own array) and their ``bands`` and
        ``counts`` measured again.  Cost at 1600x1200: about 1 ms a frame without print
        (the share of print per tile), more where there is.

        Returns
        -------
        numpy.ndarray
            The image the bands were measured on.
        """
        cfg = self.config
        length = cfg.bands.print_block_px
        if length <= cfg.bands.print_fill_px or image is raw:
            return image
        row_y = self._row_y
        h, w = raw.shape[:2]
        tile = BLOCK_TILE_PX
        printed = _print_tiles(raw, image, self._read_rows, tile)
        if not printed.any():
            return image
        for p in range(2):
            bd.band_slants(bands[p], counts[p], row_y)
        # along the long segment an upright line moves by at most a pixel
        limit = 2.0 / (length - 1)
        up = [printed & bd.upright_tiles(bands[p], counts[p], row_y, (h, w), tile, limit)
              for p in range(2)]
        redo = np.zeros(len(row_y), bool)
        for p in range(2):
            if up[p].any():
                redo |= _rejected_in(bands[p], counts[p], row_y, up[p], tile, w)
        if not redo.any():
            return image
        # whole cells: the rows of a cell share one segmentation level
        k = self._rows_per_cell
        cells = np.flatnonzero(redo.reshape(-1, k).any(axis=1))
        redo_rows = (cells[:, None] * k + np.arange(k)[None, :]).ravel()
        extra = np.arange(-cfg.bands.vertical_extra, cfg.bands.vertical_extra + 1)
        fill_rows = np.unique(np.clip(row_y[redo_rows][:, None] + extra, 0, h - 1))
        long = bd.fill_print(raw, length, cfg.bands.min_contrast * self._full_scale, fill_rows)
        noise = 3.0 * bd.column_noise(np.ascontiguousarray(raw).reshape(h, -1))
        n_c = raw.shape[2]
        before_rows = raw.reshape(h, -1)[fill_rows]
        long_rows = long.reshape(h, -1)[fill_rows]
        out_rows = image.reshape(h, -1)[fill_rows]
        changed = np.zeros(len(fill_rows), bool)
        for p in range(2):
            c = self.channels[p]
            before = np.ascontiguousarray(before_rows[:, c::n_c])
            after = long_rows[:, c::n_c]
            # the unlit level along the row (over the detector's window, two intervals):
            # print keeps a share of the light, a dip down to that level is a gap
            floor = cv2.erode(before, np.ones((1, int(self._windows[p])), np.uint8))
            lit = before.astype(np.int32) - floor
            keep = (8 * lit > after.astype(np.int32) - floor) & (lit > noise)
            keep &= np.repeat(up[p][fill_rows // tile], tile, axis=1)[:, :w]
            # near the image's border the segment is cut short: its envelope spans fewer
            # of a photo block's cells, and the bands read too unevenly
            keep[(fill_rows < length // 2) | (fill_rows >= h - length // 2)] = False
            keep &= after != out_rows[:, c::n_c]
            changed |= keep.any(axis=1)
            np.copyto(out_rows[:, c::n_c], after, where=keep)
        # (image is fill_print's own contiguous array: the reshape is a view)
        image.reshape(h, -1)[fill_rows] = out_rows
        # measured again only where the long fill changed what the detector reads (text
        # alone is filled by the short one already)
        read = np.clip(row_y[redo_rows][:, None] + extra, 0, h - 1)
        again = np.isin(read, fill_rows[changed]).any(axis=1).reshape(-1, k).any(axis=1)
        if not again.any():
            return image
        redo_rows = redo_rows.reshape(-1, k)[again].ravel()
        sub = self._detect(image, weights, row_y[redo_rows], self._windows, k)
        bands[:, redo_rows] = sub[0]
        counts[:, redo_rows] = sub[1]
        return image

    def _response_from_still_lines(self, frame, grids, timings):
        """Measure the camera's response on the lines that stood still since the last frame.

        Between the first frames (:data:`STILL_LINE_FRAMES`) a wall's lines stand
        still: :func:`~lightflow.app.core.response.find_gamma` over them, each
        candidate measuring this frame's bands again.  When the camera is not
        linear, this frame and the previous one are measured again linearised
        (the flow model finds its still lines against the previous one) and
        ``(bands, counts, grids)`` returned; else None.
        """
        prev = self._gamma_prev
        # kept for the next frame's comparison, never past the last frame that compares
        self._gamma_prev = (frame, grids) if self._frames < STILL_LINE_FRAMES[-1] else None
        if prev is None or self._frames not in STILL_LINE_FRAMES:
            return None
        still = still_lines(grids, prev[1])
        if np.count_nonzero(still) < rsp.MIN_STILL_LINES:
            return None
        keep = still.reshape(2, -1)
        # the candidates' bands go to their own scratch: this frame's stay in the pipeline's
        scratch = tuple(np.empty_like(b) for b in self._buffers)

        found = rsp.find_gamma(
            lambda lg: self.still_line_excess(float(np.exp(lg)), [frame], keep, scratch),
            rsp.MIN_STILL_LINES)  # fmt: skip
        self.camera_gamma = 1.0
        if found is None:
            return None
        self.camera_gamma, self.gamma_measured, _ = found
        self.gamma_source = "still lines"
        self._gamma_prev = None
        if self.camera_gamma == 1.0:
            return None
        self.flow_model.replace_previous(self._measure(prev[0], {}, scratch)[2])
        return self._measure(frame, timings)

    def still_line_excess(self, gamma: float, frames, keep=None, buffers=None):
        """How much wider the static lines of ``frames`` read, linearised with ``gamma``.

        Sets :attr:`camera_gamma` to ``gamma`` and measures the frames' bands
        (into ``buffers``, default the pipeline's scratch); then
        :func:`~lightflow.app.core.profile_model.static_width_excess` over their
        static lines, or only over the grid cells ``keep`` (``(2, h * w)`` bool).

        Returns
        -------
        (float, int) or None
            The median excess width (camera px) and the lines it is over.
        """
        self.camera_gamma = gamma
        samples = np.concatenate(
            [self.flow_model.line_samples(self._measure(f, {}, buffers)[2]) for f in frames],
            axis=2)  # fmt: skip
        m, r, line = (samples[:, c] if keep is None else samples[:, c][keep] for c in range(3))
        return static_width_excess(m.ravel(), r.ravel(), line.ravel(),
                                   min_bands=rsp.MIN_STILL_LINES)  # fmt: skip

    @property
    def crosstalk(self) -> tuple[np.ndarray, str]:
        """Per pattern, the colour crosstalk subtracted now (NaN where none is known yet),
        and where it came from: ``option``, ``rig`` or ``frames`` (``""``: not yet)."""
        if self.config.crosstalk != "auto":
            return np.full(2, float(self.config.crosstalk)), "option"
        if self._rig_leak is not None:
            return self._rig_leak.copy(), "rig"
        known = np.where(self._leak_known, self._leak, np.nan)
        return known, "frames" if self._leak_known.any() else ""

    def estimate_crosstalk(self, frame) -> np.ndarray:
        """Per pattern (file order), the share of the other pattern's light that its camera
        channel sees in ``frame``: NaN where the frame shows too few clean gaps for it.

        What ``crosstalk = "auto"`` estimates now and then; the pipeline's leak and learnt
        windows are unchanged.  On still lines (``lightflow rig blur``) it is the rig's
        crosstalk.
        """
        return self._crosstalk_in(self._prepared(frame))

    def _crosstalk_in(self, image: np.ndarray) -> np.ndarray:
        a, b = self.channels
        wins = self._windows if self._windows is not None else (61, 61)
        return np.array([bd.estimate_leak(image, a, b, (wins[0], wins[1])),
                         bd.estimate_leak(image, b, a, (wins[1], wins[0]))])  # fmt: skip

    def _prepared(self, frame) -> np.ndarray:
        """``frame``'s image, its size checked, in linear values (the full scale set)."""
        image = frame.image
        cam = self.rig.camera
        if image.shape[:2] != (cam.height, cam.width) or image.ndim != 3:
            raise FrameError(
                f"frame {frame.stem}: {image.shape[1]}x{image.shape[0]}, expected "
                f"{cam.width}x{cam.height} (camera.width x camera.height)"
            )
        # a 12-bit camera's full scale is 4095, not the uint16 maximum
        self._full_scale = getattr(frame, "full_scale", 65535.0 if image.dtype == np.uint16
                                   else 255.0)  # fmt: skip
        return self._linearise(image)

    def _linearise(self, image: np.ndarray) -> np.ndarray:
        """``image`` in linear values (and the full scale set to theirs), unless the camera is."""
        gamma = self.camera_gamma
        if gamma == 1.0:
            return image
        key = (image.dtype.str, self._full_scale, gamma)
        if self._linear_table is None or self._linear_table[0] != key:
            table = rsp.linearising_table(gamma, image.dtype, self._full_scale)
            self._linear_table = (key, table)
        self._full_scale = rsp.LINEAR_FULL
        return rsp.linearise(image, self._linear_table[1])

    def _causes(self, bands, counts, grids, why, raw, log_ratio, depth_grid) -> np.ndarray:
        """One :mod:`.causes` code per grid pixel: ``DEPTH`` or the first reason for none."""
        gh, gw = self.grid_shape
        per_pattern = np.empty((2, gh, gw), np.uint8)
        for p in range(2):
            reach = 0.5 * float(self._windows[p])  # about one line interval
            cz.band_causes(bands[p], counts[p], self._rows_per_cell, self.config.stride, gw,
                           reach, per_pattern[p])  # fmt: skip
        causes = np.empty((gh, gw), np.uint8)
        # between valid bands (a finite interval) the band stage let the cell through
        cz.merge_causes(per_pattern, grids[:, 1], why, log_ratio, depth_grid, causes)
        return causes

    def _warnings(self, counts) -> list[str]:
        """Frame-level warnings: most pixels with lines out of the model's range.

        Bands of any length are measured (beyond the tables their width is the
        sweep), so what falls out of the range are lines wider than the tables.
        """
        lit = int(counts.sum() - counts[cz.NO_LINES])
        if lit == 0 or counts[cz.MODEL_RANGE] < 0.5 * lit:
            return []
        share = 100.0 * counts[cz.MODEL_RANGE] / lit
        return [f"{share:.0f} % of the lit pixels are out of the model's range: projected "
                f"lines wider than the profile tables (16 camera px): use thinner lines "
                f"(the patterns' width_px)"]  # fmt: skip


def _print_tiles(raw, filled, rows, tile) -> np.ndarray:
    """Tiles (``tile`` pixels) where the short print fill changed at least
    :data:`BLOCK_PRINT_SHARE` of the values of ``rows``, pooled with the 8 tiles around.

    ``filled``: ``raw`` after :func:`~lightflow.app.core.bands.fill_print` of ``rows``
    (sorted).  The fill replaces a pixel's channels together, so the share of changed
    values is that of changed pixels.
    """
    h, w = raw.shape[:2]
    th, tw = -(-h // tile), -(-w // tile)
    flat_raw = raw.reshape(h, -1)
    flat_filled = filled.reshape(h, -1)
    step = int(rows[1] - rows[0]) if len(rows) > 1 else 1
    if step > 0 and len(rows) and np.all(np.diff(rows) == step):
        # evenly spaced rows (every grid row's): strided views, which OpenCV reads in
        # place, instead of copies of the rows (0.3-1.6 ms)
        sel = slice(int(rows[0]), int(rows[-1]) + 1, step)
        changed = cv2.compare(flat_filled[sel], flat_raw[sel], cv2.CMP_NE)
    else:
        changed = cv2.compare(flat_filled[rows], flat_raw[rows], cv2.CMP_NE)
    # sums over the rows of each tile row, then over each tile's columns
    bounds = np.searchsorted(rows, np.arange(th + 1) * tile)
    per_row = np.zeros((th, tw * tile * flat_raw.shape[1] // w), np.float32)
    for t in range(th):
        if bounds[t + 1] > bounds[t]:
            # OpenCV's sum over rows: a tenth of the time of numpy's reduceat
            per_row[t, : flat_raw.shape[1]] = cv2.reduce(
                changed[bounds[t] : bounds[t + 1]], 0, cv2.REDUCE_SUM, dtype=cv2.CV_32S)[0]
    hits = per_row.reshape(th, tw, -1).sum(axis=2) / 255.0
    n_rows = np.diff(bounds).astype(np.float32)
    total = n_rows[:, None] * np.full(tw, tile * flat_raw.shape[1] // w, np.float32)
    total[:, -1] -= n_rows * (tw * tile - w) * (flat_raw.shape[1] // w)
    # pooled with the neighbours: a photo block's own tile may hold little text
    hits = cv2.boxFilter(hits, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
    total = cv2.boxFilter(total, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
    return hits >= BLOCK_PRINT_SHARE * np.maximum(total, 1.0)


def _rejected_in(bands, counts, row_y, upright, tile, width) -> np.ndarray:
    """Per measured row: does it hold a cut, irregular or overlapping band in an upright
    tile (``upright``, tiles of ``tile`` pixels)?  Bands at the image border are cut by
    it, not by print, and do not count."""
    bands = bands[:, : max(1, int(counts.max(initial=0)))]  # the rest is unused scratch
    n = np.arange(bands.shape[1])[None, :] < counts[:, None]
    code = bands[..., bd.F_VALID]
    start = bands[..., bd.F_START]
    end = bands[..., bd.F_END]
    border = (start <= 0) | (end >= width - 1) | (
        (code == bd.BAND_CUT) & np.isnan(bands[..., bd.F_CENTRE]))
    bad = n & ~border & ((code == bd.BAND_CUT) | (code == bd.BAND_IRREGULAR)
                         | (code == bd.BAND_OVERLAP))  # fmt: skip
    mid = np.nan_to_num(0.5 * (start + end))
    col = np.clip(mid // tile, 0, upright.shape[1] - 1).astype(np.int64)
    rows = np.broadcast_to((row_y // tile)[:, None], col.shape)
    return (bad & upright[rows, col]).any(axis=1)


def _band_set(channel: str, bands: np.ndarray, counts: np.ndarray, row_y: np.ndarray) -> BandSet:
    n = int(counts.sum())
    rows = np.empty(n, np.float32)
    starts = np.empty(n, np.float32)
    ends = np.empty(n, np.float32)
    valid = np.empty(n, np.bool_)
    m = bd.pack_bands(bands, counts, row_y, rows, starts, ends, valid)
    return BandSet(channel, rows[:m], starts[:m], ends[:m], valid[:m])


def warm_up_kernels() -> None:
    """Compile (or load) the kernels of :meth:`DepthPipeline._arc_intervals` (with the
    rasterising of the grid rows the arcs change) and
    :meth:`DepthPipeline._depth_from_intervals`, with a frame's argument types.

    A test image of straight stripes reaches neither (no interval changes, no lines that
    move too little): on a cold start they compiled in the first frame.
    :meth:`DepthPipeline.warm_up_optional` calls this; the demo calls it before it waits
    for its helper process.
    """
    grids = np.zeros((2, 4, 4, 4))
    rows = np.array([0, 2], np.int64)
    old = grids.take(rows, axis=2)
    bands = np.full((1, 2, bd.N_FIELDS), np.nan)
    fields = np.array(bd.GRID_FIELDS, np.int64)
    bd.rasterise_cells(bands, np.zeros(1, np.int64), 1, 4, 4, 0.5, fields, grids[0], rows[:1])
    ratio = np.empty((2, 2, 4))
    changed = np.empty((2, 4), np.bool_)
    _compare_rows(old, grids, rows, ratio, changed)
    _shift_rows(ratio, rows, changed, np.zeros((2, 4, 4), np.float32), np.zeros((4, 4), bool))
    f32 = np.zeros((4, 4), np.float32)
    _interval_variance(grids[:, 1], f32, 1.0, INTERVAL_NOISE**2, INTERVAL_FLOOR**2, f32.copy(), 0,
                       4)  # fmt: skip
    flags = np.zeros((4, 4), bool)
    one = np.float32(1.0)
    _join_interval_depth(f32, f32.copy(), flags, flags.copy(), one, one, one, f32.copy(),
                         f32.copy(), 0, 4)  # fmt: skip


# The kernels below fuse what were numpy passes over the rows that the arcs changed
# (:meth:`DepthPipeline._arc_intervals`), with numpy's arithmetic.


@nb.njit(cache=True, error_model="numpy", nogil=True, **NO_CFUNC)
def _compare_rows(old, grids, rows, ratio, changed):
    """``ratio``: per pattern, the old interval (``old[:, 1]``, rows ``rows`` of ``grids``
    as they were) over the new; ``changed``: with the four fields in ``old``, whether
    another field of the cell changed (NaN-aware: a cell that gained a band)."""
    for q in range(rows.size):
        i = rows[q]
        for j in range(ratio.shape[2]):
            c = False
            for p in range(2):
                ratio[p, q, j] = old[p, 1, q, j] / grids[p, 1, i, j]
                if old.shape[1] > 2:
                    for f in (0, 2, 3):
                        a = old[p, f, q, j]
                        b = grids[p, f, i, j]
                        if a != b and not (np.isnan(a) and np.isnan(b)):
                            c = True
            changed[q, j] = c


@nb.njit(cache=True, error_model="numpy", nogil=True, **NO_CFUNC)
def _shift_rows(log_ratio, rows, changed, shift, added):
    """``shift`` (float32): ``log_ratio`` (per pattern, on rows ``rows``), 0 where it is not
    finite; ``added``: a shift other than 0, or ``changed``."""
    for q in range(rows.size):
        i = rows[q]
        for j in range(shift.shape[2]):
            a = changed[q, j]
            for p in range(2):
                v = log_ratio[p, q, j]
                s = np.float32(v) if np.isfinite(v) else np.float32(0.0)
                shift[p, i, j] = s
                a = a or s != 0.0
            added[i, j] = a


@nb.njit(cache=True, error_model="numpy", nogil=True, **NO_CFUNC)
def _interval_variance(intervals, sens, cells, noise_var, floor_var, var, i0, i1):
    """``var`` (float32): the variance of the log depth from the intervals, ``(noise_var /
    bands + floor_var) / sens^2``, ``bands`` (at least 1) being ``cells`` over the mean of
    the two intervals; in float64 as numpy, ``sens^2`` in float32.  Rows ``i0 .. i1``."""
    for i in range(i0, i1):
        for j in range(var.shape[1]):
            x = cells / ((intervals[0, i, j] + intervals[1, i, j]) / 2.0)
            bands = x if x > 1.0 or np.isnan(x) else 1.0  # np.maximum: NaN stays
            s2 = sens[i, j] * sens[i, j]
            var[i, j] = (noise_var / bands + floor_var) / s2


@nb.njit(cache=True, error_model="numpy", nogil=True, **NO_CFUNC)
def _join_interval_depth(z, var, swept, curved, max_std, near, far, depth, std, i0, i1):
    """:meth:`DepthPipeline._depth_from_intervals`' last step on rows ``i0 .. i1``: the
    interval depth ``z`` (its std ``z * sqrt(var)``) where it is within ``max_std`` of it
    and ``near .. far``: it fills ``depth`` and ``std`` (in place) where they have none, and
    is averaged with them by precision where a swept cell does not bend (float32 as
    numpy)."""
    one = np.float32(1.0)
    for i in range(i0, i1):
        for j in range(z.shape[1]):
            zz = z[i, j]
            s = zz * np.sqrt(var[i, j])
            if not (s <= max_std * zz and zz >= near and zz <= far):
                continue
            d = depth[i, j]
            if not np.isfinite(d):
                depth[i, j] = zz
                std[i, j] = s
            elif swept[i, j] and not curved[i, j]:
                w_flow = one / (std[i, j] * std[i, j])
                w_int = one / (s * s)
                depth[i, j] = (d * w_flow + zz * w_int) / (w_flow + w_int)
                std[i, j] = one / np.sqrt(w_flow + w_int)


def _near(depth: np.ndarray) -> np.ndarray:
    """The cells within :data:`MOVED_NEAR_DEPTH_CELLS` of a finite ``depth`` cell."""
    near = cv2.dilate(np.isfinite(depth).view(np.uint8),
                      np.ones((2 * MOVED_NEAR_DEPTH_CELLS + 1,) * 2, np.uint8))
    return near.view(bool)


def _enclosed(depth: np.ndarray) -> np.ndarray:
    """The cells with a finite ``depth`` or enclosed by them, over gaps of up to
    ``2 * ENCLOSE_GAP_CELLS`` cells."""
    has = cv2.dilate(np.isfinite(depth).view(np.uint8),
                     np.ones((2 * ENCLOSE_GAP_CELLS + 1,) * 2, np.uint8))
    h, w = has.shape
    # flood the outside from a border of zeros around the grid
    outside = np.zeros((h + 2, w + 2), np.uint8)
    outside[1:-1, 1:-1] = has
    cv2.floodFill(outside, np.zeros((h + 4, w + 4), np.uint8), (0, 0), 2)
    return outside[1:-1, 1:-1] != 2
