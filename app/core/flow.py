"""From band lengths and intervals to light flows and their log ratio (pure numpy/OpenCV).

Flow of pattern i in line-index units is ``L_i / B_i`` (sweep over the local
line interval); in projector pixels it is that times the local pitch
``P_i(u)``.  Two projectors: ``log ratio = log(L_1/B_1) - log(L_2/B_2)``.  One
projector with the exp2 pair: both patterns share the sweep, so the ratio of
the flows is the ratio of the intervals, ``B_2 / B_1``, which is measured far
more precisely than a sweep; the sweeps still decide which pixels move.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numba as nb
import numpy as np

from . import causes as cz
from .depth_model import pattern_params, pitch_at
from .errors import ConfigError
from .kernel_options import NO_CFUNC
from .patterns import local_pitch
from .profile_model import (
    L_AXIS,
    M_STEP,
    R_STEP,
    S_AXIS,
    W_STEP,
    fit_blur,
    joint_at,
    static_blur,
    tables,
    trilinear_at,
)
from .rig import Rig
from .threads import run_rows, run_tasks, threads

#: values of :attr:`FlowParams.static_depth`
STATIC_DEPTH_MODES = ("auto", "on", "off")

#: early frames on which the blur model is refitted while its pool of bands fills
BLUR_EARLY_REFITS = (1, 2, 4, 8)


@dataclass(frozen=True)
class FlowParams:
    """Options of the flow stage.

    Attributes
    ----------
    smoothing_px : float
        Gaussian sigma, in camera pixels, of the masked smoothing of the log
        flow ratio (the paper uses 2 to 60); 0 disables it.
    static_factor : float
        A band counts as moving only if its sweep, averaged over a few cells,
        exceeds the line width in camera pixels times this factor plus
        ``static_margin_px``.
    static_margin_px : float
    calibrated_static_factor, calibrated_static_margin_px : float
        The same with a measured blur (by ``lightflow rig blur``, or on lines that
        stand still between the first frames, a wall): a sweep shorter than the
        line only shows in the ramps, against the blur, so a known blur lets
        shorter sweeps count.
    measure_factor, measure_margin_px : float
        Sweeps of single cells below ``measure_factor`` line widths plus
        ``measure_margin_px`` are not measured at all (a static line).
    sweep_smoothing_px : float
        Gaussian sigma (camera px) of the averaging of the sweeps of each
        pattern before the moving test and the log ratio.
    sweep_outlier : float
        Cells whose sweep differs from that average by more than this fraction
        of it are dropped (another surface).
    measured_share : float
        Cells where less than this share of the banded cells around have a
        measurable sweep are dropped (sweeps at the floor, selected by noise).
    outlier_sigmas : float
        Pixels whose log ratio is further than this many robust deviations
        from the smoothed field are dropped before the final smoothing.
    static_depth : str
        Single projector only: ``"auto"`` or ``"on"`` also gives depth where the
        lines stand still (the depth is in the ratio of the line intervals,
        which needs no motion); ``"off"`` only where they move.  Two-projector
        rigs need motion: ``"on"`` is refused there.
    """

    smoothing_px: float = 24.0
    static_factor: float = 0.9
    static_margin_px: float = 1.0
    # chosen on the tuning rigs with their measured blur (fan 1 ms, balls 5 and 8 ms:
    # coverage 5-25 % -> 14-34 %, the fan's median 5.9 -> 12.7 mm, the balls' within 1 mm;
    # then 0.6 + 0.5 px -> 0.45 + 0.3 px with the measure floor below 0.5 + 0.5 px -> 0.3 +
    # 0.3 px: the fan 41 -> 50 % at 10.2 -> 13.9 mm, the balls +1 to +6 points within 1 mm)
    calibrated_static_factor: float = 0.45
    calibrated_static_margin_px: float = 0.3
    measure_factor: float = 0.3
    measure_margin_px: float = 0.3
    sweep_smoothing_px: float = 8.0
    sweep_outlier: float = 0.4
    measured_share: float = 0.6
    fill_fraction: float = 0.3
    outlier_sigmas: float = 3.0
    blur_refit_frames: int = 30
    static_depth: str = "auto"

    def __post_init__(self):
        if self.static_depth not in STATIC_DEPTH_MODES:
            raise ConfigError(f"static_depth: expected one of {', '.join(STATIC_DEPTH_MODES)}, "
                              f"got {self.static_depth!r}")  # fmt: skip


@dataclass(frozen=True)
class FlowMaps:
    """What :meth:`FlowModel.combine` finds on the analysis grid (NaN = no value).

    Attributes
    ----------
    log_ratio : numpy.ndarray
        Raw log flow ratio, before the final smoothing.
    flows : list of numpy.ndarray
        Per pattern, the flow in projector pixels.
    blur_px : list of float
        Per pattern, the blur sigma (camera px) at the median magnification.
    lr_var : numpy.ndarray
        Random error of ``log_ratio``: its variance.
    lr_sys : numpy.ndarray
        Systematic error of ``log_ratio`` (blur model), one standard deviation.
    why : numpy.ndarray
        uint8 :mod:`lightflow.app.core.causes` code: ``DEPTH`` where ``log_ratio`` is
        finite, else why not.
    swept : numpy.ndarray
        bool: both patterns' bands in the cell are measurably wider than a line
        standing still (above the measure floor), whether or not they pass the
        moving test: lines that move, if too little for a flow.
    readings : tuple of numpy.ndarray, optional
        Each cell's own reading of its bands, before the sweeps are averaged over
        cells (``_sweeps``' outputs: sweeps, moving_at, pitch, sens,
        interval_ratio, banded, why): :meth:`FlowModel.reread` reads again only the
        cells whose intervals it corrects.
    """

    log_ratio: np.ndarray
    flows: list
    blur_px: list
    lr_var: np.ndarray
    lr_sys: np.ndarray
    why: np.ndarray
    swept: np.ndarray
    readings: tuple | None = None

    def screen(self, depth, slope, noise_gain, floor_var, max_rel_std):
        """Drop the cells whose depth is out of range or too uncertain; their predicted variance.

        The predicted error of a cell's log ratio is ``lr_var * noise_gain + lr_sys ** 2
        + floor_var`` (a variance); times the depth's slope it is the depth's.  One
        pass over the maps (the numpy expressions it replaces cost a temporary each).
        :attr:`why` is updated in place: ``DEPTH_RANGE`` where a finite log ratio has
        no depth, then ``UNCERTAIN`` where the depth's error is too large.

        Parameters
        ----------
        depth, slope : numpy.ndarray
            ``(h, w)`` float32: the depth of :attr:`log_ratio` and ``|dz / dlog_ratio|``
            (:func:`lightflow.app.core.depth_model.depth_and_slope`).
        noise_gain, floor_var, max_rel_std : float
            Scale of :attr:`lr_var`, the variance added, and the largest depth error
            kept, as a share of the depth.

        Returns
        -------
        (numpy.ndarray, numpy.ndarray)
            ``(h, w)`` float32: the log ratio where it has a certain enough depth, else
            NaN, and the depth's predicted variance (m^2) on every cell.
        """
        kept = np.empty(self.log_ratio.shape, np.float32)
        variance = np.empty(self.log_ratio.shape, np.float32)
        # float32 constants: numpy multiplies a float32 map by a Python float in float32
        run_rows(_screen, kept.shape[0], self.log_ratio, depth, slope, self.lr_var, self.lr_sys,
                 np.float32(noise_gain), np.float32(floor_var), np.float32(max_rel_std),
                 self.why, kept, variance)  # fmt: skip
        return kept, variance


#: the per-band ramp solve of :func:`fit_blur` comes out about 10 % low in sigma (noisy
#: ramps through a non-linear inverse); short sweeps read with too small a blur come out
#: long, one pattern more than the other.  Scaling sigma^2 by this moved the signed error
#: towards 0 on every case of the tuning rigs (boards, fans, balls; `make eval`
#: --tuning-rigs): fan 1 ms +11.8 -> +5.9 and +12.7 -> +0.3 mm, balls 8 ms +15.8 -> +9.0 mm
BLUR_FIT_GAIN = 1.25

#: frames whose moving bands are pooled for the blur fit
BLUR_POOL_FRAMES = 8
#: frames compared with the one before for lines that stand still (a wall behind a fan):
#: early ones, which every replay and batch chunk replays in order
STILL_LINE_FRAMES = (1, 2)
#: a grid cell's band width and line interval agree this closely between two frames
#: where its line stands still (camera px)
STILL_TOLERANCE_PX = 0.1
#: a grid cell's line moved between two frames where its band width or line interval
#: (measured in both) changed by more than this (camera px): five times the still lines'
#: tolerance, above the measurements' noise on a rotating fan's hub (at 0.1 px a tuning
#: fan's hub read as moved and 7 % of its depth went onto it)
MOVED_TOLERANCE_PX = 0.5
#: still-line measurements needed to trust them over the fit on moving bands
STILL_MIN_LINES = 2000
#: ... seen over magnifications that span this ratio (else the two parts of the blur
#: cannot be told apart)
MIN_STILL_SPAN = 1.15


#: relative error of the fitted blur sigma that the uncertainty allows for: a sweep
#: shorter than the line is read from its ramps, and there it depends on the blur
BLUR_REL_ERROR = 0.1
#: the same for a blur measured on still lines (``lightflow rig blur``): within 1-5 % of
#: the simulator's optics in tests/test_blurcal.py
CALIBRATED_BLUR_REL_ERROR = 0.05


@nb.njit(cache=True, error_model="numpy", nogil=True, **NO_CFUNC)
def _sweeps(
    grids, intervals, kinds, steps, widths, line_px, blur, single, u_lo, u_step, u_of,
    inv, inv_m, s_lo, s_step, w_step, m_step, r_step, m_max, lo_factor, lo_margin,
    static_factor, static_margin, blur_known, blur_rel_error, still_depth, periodic, todo,
    sweeps, moving_at, pitch, interval_ratio, banded, sens, why, i0, i1,
):  # fmt: skip
    """Per grid pixel and pattern: the sweep in line-index units ``L / B`` (see FlowModel.combine).

    The line intervals ``B`` are read from ``intervals`` (``(2, h, w)``), the other
    fields from ``grids``.

    ``moving_at[p]``: the sweep (index units) above which the line clearly moves;
    ``banded``: 1 where both patterns have a band (moving or not), else 0;
    ``pitch[p]``: the local pitch in projector px; ``interval_ratio``: log(B1 / B0);
    ``sens[p]``: how much the sweep (index units) changes when the blur sigma is
    off by ``blur_rel_error`` (signed: both patterns share one blur model);
    ``why``: a :mod:`.causes` code for cells without sweeps, else ``DEPTH``.
    With ``still_depth`` (single projector), ``interval_ratio`` is kept on every
    cell whose intervals the patterns can make, moving or not.
    Cells whose sweep is hidden in the line width (below ``lo_factor * line +
    lo_margin``) or whose bands fill the interval get NaN, unless ``periodic[p]`` marks
    the cell's sweep as measured on the periodic profile of overlapping bands.  Grid
    rows ``i0 .. i1`` only (the kernels of this module run bands of rows on a thread per
    core).  Only the cells where ``todo`` is true are read; the others keep what the
    outputs hold.
    """
    gw = interval_ratio.shape[1]
    nu = u_of.shape[0]
    for i in range(i0, i1):
        for j in range(gw):
            if not todo[i, j]:
                continue
            interval_ratio[i, j] = np.nan
            banded[i, j] = 0.0
            why[i, j] = cz.DEPTH
            for p in range(2):
                sweeps[p, i, j] = np.nan
                moving_at[p, i, j] = np.nan
                sens[p, i, j] = 0.0
            B0 = intervals[0, i, j]
            B1 = intervals[1, i, j]
            if not (B0 > 0.0 and B1 > 0.0):
                why[i, j] = cz.NO_LINES
                continue
            if np.isfinite(grids[0, 0, i, j]) and np.isfinite(grids[1, 0, i, j]):
                banded[i, j] = 1.0
            u = 0.0
            ir = math.log(B1 / B0)
            if single:
                t = (ir - u_lo) / u_step
                if not (t >= 0.0 and t <= nu - 1):
                    why[i, j] = cz.IRREGULAR  # an interval ratio the patterns cannot make
                    continue
                k = min(int(t), nu - 2)
                u = u_of[k] + (t - k) * (u_of[k + 1] - u_of[k])
            for p in range(2):
                m = grids[p, 0, i, j]
                B = intervals[p, i, j]
                slant = grids[p, 3, i, j]
                if not np.isfinite(slant):
                    slant = 0.0
                P = pitch_at(kinds[p], steps[p], widths[p], u)
                scale = B / P
                line = line_px[p] * scale
                # camera blur is isotropic: along a row it widens a slanted edge
                sigma = math.sqrt(blur[p, 0] * (1.0 + slant * slant) + blur[p, 1] * scale * scale)
                r = grids[p, 2, i, j]
                if line > (inv_m.shape[1] - 1) * w_step:
                    why[i, j] = cz.MODEL_RANGE  # a line wider than the profile tables
                    break
                short = not (m >= m_max or m > line + 4.0 * sigma + 2.0)
                L = np.nan
                spread = 0.0  # the sweep's change for a blur larger by blur_rel_error
                if m >= m_max:
                    # far beyond line width and blur: the width at half height is the sweep
                    L = m
                elif not short:
                    # a long band: its ramps are the line edge, its width alone decides
                    # (the same answer as the joint inverse, for half the memory reads)
                    L = trilinear_at(inv_m, s_lo, s_step, w_step, m_step, sigma, line, m)
                elif blur_known:
                    # width and ramp together: a sweep shorter than the line shows in the
                    # ramps, and there it depends on the blur: read it at two blurs
                    for k in range(2):
                        sg = sigma * (1.0 + k * blur_rel_error)
                        v = joint_at(inv, s_lo, s_step, w_step, m_step, r_step, sg, line, m, r)
                        if k == 0:
                            L = v
                        elif np.isfinite(v):
                            spread = v - L
                        else:
                            spread = L - lo_factor * line  # at the edge of the tables
                if not np.isfinite(L):
                    if not blur_known and short:
                        # a band no wider than its line is static (or too short to tell);
                        # a wider one is a short sweep that needs the fitted blur
                        why[i, j] = cz.BLUR_UNKNOWN if m > line + 1.0 else cz.STATIC
                    elif np.isfinite(m):
                        why[i, j] = cz.MODEL_RANGE
                    else:
                        why[i, j] = cz.NO_LINES
                    break
                if not (L > lo_factor * line + lo_margin):
                    why[i, j] = cz.STATIC  # no measurable sweep: a (nearly) static line
                    break
                if L + line + 1.0 * sigma > B and not periodic[p, i, j]:
                    why[i, j] = cz.OVERLAP  # swept line and its blur fill the interval
                    break
                sens[p, i, j] = spread / B
                sweeps[p, i, j] = L / B
                moving_at[p, i, j] = (static_factor * line + static_margin) / B
                pitch[p, i, j] = P
            if still_depth:
                interval_ratio[i, j] = ir  # the depth needs no sweep (see _decide)
            if why[i, j] != cz.DEPTH:
                for p in range(2):
                    sweeps[p, i, j] = np.nan
                continue
            interval_ratio[i, j] = ir


#: channels of the stack averaged around each cell: the two sweeps, where both are
#: valid, where both patterns have bands, then the sweeps squared (two projectors) or
#: the interval ratio and its square (one projector: the ratio is in the intervals)
N_STACK = 6
#: one projector: a seventh channel, where the interval ratio is valid (it may be
#: without sweeps: lines that stand still)
N_STACK_SINGLE = 7


#: floats in OpenCV's widest vectors (AVX-512; see :func:`_gauss_window`)
SIMD_COLUMNS = 16
#: :meth:`FlowModel.reread` decides again the tiles of these many grid rows and columns
#: near the cells it reads again
REREAD_TILE = (8, 16)
#: what a window of :meth:`FlowModel.reread` costs besides its cells (its calls, about
#: 40 us), in cells blurred
WINDOW_CALL_CELLS = 4000.0


@nb.njit(cache=True, error_model="numpy", nogil=True, **NO_CFUNC)
def _pack(sweeps, banded, interval_ratio, single, stack, busy, i0, i1):
    """Fill the channels of ``stack`` (0 where the sweeps or the interval ratio are invalid).

    :data:`N_STACK` channels for two projectors, :data:`N_STACK_SINGLE` for one.
    ``busy[i]``: whether row ``i`` of ``stack`` has a channel other than 0.
    Grid rows ``i0 .. i1`` only.
    """
    gw = stack.shape[1]
    for i in range(i0, i1):
        any_data = False
        for j in range(gw):
            stack[i, j, 3] = banded[i, j]
            a = sweeps[0, i, j]
            b = sweeps[1, i, j]
            if np.isfinite(a) and np.isfinite(b):
                stack[i, j, 0] = a
                stack[i, j, 1] = b
                stack[i, j, 2] = 1.0
                if not single:
                    stack[i, j, 4] = a * a
                    stack[i, j, 5] = b * b
            else:
                for c in (0, 1, 2):
                    stack[i, j, c] = 0.0
                if not single:
                    stack[i, j, 4] = 0.0
                    stack[i, j, 5] = 0.0
            if single:
                ir = interval_ratio[i, j]
                if np.isfinite(ir):
                    stack[i, j, 4] = ir
                    stack[i, j, 5] = ir * ir
                    stack[i, j, 6] = 1.0
                else:
                    stack[i, j, 4] = 0.0
                    stack[i, j, 5] = 0.0
                    stack[i, j, 6] = 0.0
            # every other channel is 0 where these are (NaN counts as data)
            if stack[i, j, 2] != 0.0 or stack[i, j, 3] != 0.0 or (single and stack[i, j, 6] != 0.0):
                any_data = True
        busy[i] = any_data


@nb.njit(cache=True, error_model="numpy", nogil=True, **NO_CFUNC)
def _decide(
    sweeps, blurred, moving_at, pitch, interval_ratio, single, still_depth, outlier, share,
    sens, intervals, cells_per_kernel, log_ratio, flows, lr_var, lr_sys, why, j0, j1, i0, i1,
):  # fmt: skip
    """Moving test on the averaged sweeps, then the log ratio, the flows (projector px)
    and the log ratio's expected error.

    A cell far from the average around it is another surface (a static wall beside a
    blade): the average must not carry it over the static limit.  The test is
    two-sided, so it does not bias what passes.  Where only a few of the banded cells
    around have a measurable sweep, the sweeps are at the floor of what can be
    measured, and the few that passed are the ones whose noise pushed them up:
    such cells are dropped (``share``).

    The error of the log ratio has a random part, ``lr_var``: the local variance
    of the sweeps over the number of independent bands averaged (cells along a
    row between two bands share them), and a systematic part, ``lr_sys``: a blur
    off by its relative error moves both sweeps at once (``sens``).

    One projector: the log ratio is the cell's interval ratio and its random
    error the local variance of that ratio.  With ``still_depth`` every cell with
    an interval ratio gets it; the moving tests then decide only the flows.
    Grid rows ``i0 .. i1``, columns ``j0 .. j1`` only.
    """
    for i in range(i0, i1):
        for j in range(j0, j1):
            log_ratio[i, j] = np.nan
            flows[0, i, j] = np.nan
            flows[1, i, j] = np.nan
            lr_var[i, j] = np.nan
            lr_sys[i, j] = np.nan
            den = blurred[i, j, 2]
            both = np.isfinite(sweeps[0, i, j]) and np.isfinite(sweeps[1, i, j])
            moving = den > 0.0 and both
            if moving and den < share * blurred[i, j, 3]:
                why[i, j] = cz.STATIC  # sweeps at the floor of what can be measured
                moving = False
            if moving:
                for p in range(2):
                    sm = blurred[i, j, p] / den
                    if not (sm > moving_at[p, i, j]):
                        why[i, j] = cz.STATIC
                    elif abs(sweeps[p, i, j] - sm) >= outlier * sm and why[i, j] == cz.DEPTH:
                        why[i, j] = cz.INCONSISTENT
                moving = why[i, j] == cz.DEPTH
            # independent bands in the kernel: valid cells, of which B / stride share a band
            interval = 0.5 * (intervals[0, i, j] + intervals[1, i, j])
            if moving:
                s0 = blurred[i, j, 0] / den
                s1 = blurred[i, j, 1] / den
                flows[0, i, j] = s0 * pitch[0, i, j]
                flows[1, i, j] = s1 * pitch[1, i, j]
                if not single:
                    n = max(1.0, cells_per_kernel * den / max(1.0, interval))
                    log_ratio[i, j] = math.log(s0 / s1)
                    v0 = max(blurred[i, j, 4] / den - s0 * s0, 0.0) / (s0 * s0)
                    v1 = max(blurred[i, j, 5] / den - s1 * s1, 0.0) / (s1 * s1)
                    lr_var[i, j] = (v0 + v1) / n
                    lr_sys[i, j] = abs(sens[0, i, j] / s0 - sens[1, i, j] / s1)
                    continue
            if not single or not (moving or still_depth):
                continue
            den_ir = blurred[i, j, 6]
            if not (den_ir > 0.0 and np.isfinite(interval_ratio[i, j])):
                continue
            why[i, j] = cz.DEPTH
            n = max(1.0, cells_per_kernel * den_ir / max(1.0, interval))
            ir = blurred[i, j, 4] / den_ir
            log_ratio[i, j] = interval_ratio[i, j]
            lr_var[i, j] = max(blurred[i, j, 5] / den_ir - ir * ir, 0.0) / n
            lr_sys[i, j] = 0.0


@nb.njit(cache=True, error_model="numpy", nogil=True, **NO_CFUNC)
def _take_again(first_lr, first_flows, first_var, first_sys, first_why, shift, grow, added,
                has_added, sweeps, log_ratio, flows, lr_var, lr_sys, why, swept, j0, j1, i0,
                i1):  # fmt: skip
    """:meth:`FlowModel.reread`'s choice between the two readings, in place on the second.

    ``log_ratio``, ``flows``, ... hold the second reading (:meth:`FlowModel.recombine`);
    where either reading has no log ratio, ``first_lr + shift[0] - shift[1]`` and
    ``first_flows * grow`` (``grow = exp(shift)``, numpy's) stand, and the first's
    errors and cause.  With ``has_added``, an ``added`` cell that only the second reading
    gives a log ratio takes the second whole, and ``swept`` where its sweeps are both
    valid.  The arithmetic is numpy's (``shift``'s dtype); grid rows ``i0 .. i1``,
    columns ``j0 .. j1`` only.
    """
    for i in range(i0, i1):
        for j in range(j0, j1):
            f = first_lr[i, j]
            s = log_ratio[i, j]
            if has_added and added[i, j]:
                if np.isfinite(sweeps[0, i, j]) and np.isfinite(sweeps[1, i, j]):
                    swept[i, j] = True
                if not np.isfinite(f) and np.isfinite(s):
                    continue  # the second reading whole
            if not (np.isfinite(f) and np.isfinite(s)):
                log_ratio[i, j] = f + shift[0, i, j] - shift[1, i, j]
                for p in range(2):
                    flows[p, i, j] = first_flows[p, i, j] * grow[p, i, j]
            lr_var[i, j] = first_var[i, j]
            lr_sys[i, j] = first_sys[i, j]
            why[i, j] = first_why[i, j]


@nb.njit(cache=True, nogil=True, **NO_CFUNC)
def _dirty_tiles(todo, reach, tile_rows, tile_cols, tiles):
    """``tiles``: the tiles of ``tile_rows`` x ``tile_cols`` cells with a cell within ``reach``
    (rows and columns) of a ``todo`` one."""
    gh, gw = todo.shape
    # per row, the columns of tiles that its runs of todo cells reach
    near = np.zeros((gh, tiles.shape[1]), np.bool_)
    for i in range(gh):
        j = 0
        while j < gw:
            if not todo[i, j]:
                j += 1
                continue
            j0 = j
            while j < gw and todo[i, j]:
                j += 1
            for tj in range(
                max(0, j0 - reach) // tile_cols, min(gw - 1, j - 1 + reach) // tile_cols + 1
            ):
                near[i, tj] = True
    for ti in range(tiles.shape[0]):
        for i in range(max(0, ti * tile_rows - reach), min(gh, (ti + 1) * tile_rows + reach)):
            for tj in range(tiles.shape[1]):
                tiles[ti, tj] |= near[i, tj]


@nb.njit(cache=True, nogil=True, **NO_CFUNC)
def _window_cost(r0, r1, c0, c1, reach, gh, gw):
    """What deciding cells ``r0 .. r1`` x ``c0 .. c1`` again costs, in cells blurred: the
    cells its blur reads (:func:`_gauss_window`), half the cells decided, and its calls."""
    rows = min(gh, r1 + reach) - max(0, r0 - reach)
    cols = min(gw, c1 + reach + SIMD_COLUMNS) - max(0, c0 - reach)
    return rows * cols + 0.5 * (r1 - r0) * (c1 - c0) + WINDOW_CALL_CELLS


@nb.njit(cache=True, nogil=True, **NO_CFUNC)
def _merge_windows(win, reach, gh, gw):
    """The windows ``win`` (``(n, 4)``: ``r0, r1, c0, c1``, disjoint) with pairs joined into
    their bounding box while that costs less (:func:`_window_cost`) and meets no other
    window, the best saving first."""
    n = win.shape[0]
    alive = np.ones(n, np.bool_)
    while True:
        best = 0.0
        bi = bj = -1
        for i in range(n):
            if not alive[i]:
                continue
            ci = _window_cost(win[i, 0], win[i, 1], win[i, 2], win[i, 3], reach, gh, gw)
            for j in range(i + 1, n):
                if not alive[j]:
                    continue
                r0, r1 = min(win[i, 0], win[j, 0]), max(win[i, 1], win[j, 1])
                c0, c1 = min(win[i, 2], win[j, 2]), max(win[i, 3], win[j, 3])
                save = (ci + _window_cost(win[j, 0], win[j, 1], win[j, 2], win[j, 3], reach, gh, gw)
                        - _window_cost(r0, r1, c0, c1, reach, gh, gw))  # fmt: skip
                if save <= best:
                    continue
                clear = True
                for k in range(n):
                    if (alive[k] and k != i and k != j and win[k, 0] < r1 and r0 < win[k, 1]
                            and win[k, 2] < c1 and c0 < win[k, 3]):  # fmt: skip
                        clear = False
                        break
                if clear:
                    best, bi, bj = save, i, j
        if bi < 0:
            return win[alive]
        win[bi, 0], win[bi, 1] = min(win[bi, 0], win[bj, 0]), max(win[bi, 1], win[bj, 1])
        win[bi, 2], win[bi, 3] = min(win[bi, 2], win[bj, 2]), max(win[bi, 3], win[bj, 3])
        alive[bj] = False


@nb.njit(cache=True, error_model="numpy", nogil=True, **NO_CFUNC)
def _screen(raw, depth, slope, lr_var, lr_sys, noise_gain, floor_var, max_rel_std, why, kept,
            variance, i0, i1):  # fmt: skip
    """:meth:`FlowMaps.screen` on grid rows ``i0 .. i1`` (float32 throughout, as numpy
    computes a float32 map with Python floats)."""
    gw = raw.shape[1]
    nan = np.float32(np.nan)
    for i in range(i0, i1):
        for j in range(gw):
            r = raw[i, j]
            z = depth[i, j]
            if np.isfinite(r) and not np.isfinite(z):
                why[i, j] = cz.DEPTH_RANGE
            v = lr_var[i, j] * noise_gain + lr_sys[i, j] * lr_sys[i, j] + floor_var
            std = np.sqrt(v) * slope[i, j]
            uncertain = std > max_rel_std * z
            if uncertain:
                why[i, j] = cz.UNCERTAIN
            kept[i, j] = r if np.isfinite(z) and not uncertain else nan
            variance[i, j] = std * std


def still_lines(grids: np.ndarray, previous: np.ndarray) -> np.ndarray:
    """Per pattern and grid cell, whether its line stood still since the previous frame.

    Parameters
    ----------
    grids, previous : numpy.ndarray
        ``(2, >=2, h, w)``: per pattern, the band width at half height and the line
        interval (the first two fields of :meth:`FlowModel.combine`'s grids) of this
        frame and the one before.

    Returns
    -------
    numpy.ndarray
        ``(2, h, w)`` bool: both agree within :data:`STILL_TOLERANCE_PX`.
    """
    with np.errstate(invalid="ignore"):
        return ((np.abs(grids[:, 0] - previous[:, 0]) < STILL_TOLERANCE_PX)
                & (np.abs(grids[:, 1] - previous[:, 1]) < STILL_TOLERANCE_PX))  # fmt: skip


def moved_lines(grids: np.ndarray, previous: np.ndarray) -> np.ndarray:
    """Per grid cell, whether a pattern's line moved since the previous frame.

    A line can stand still within an exposure and yet belong to a moving surface (a ball
    moving along its lines): between frames, such a surface's lines move.

    Parameters
    ----------
    grids, previous : numpy.ndarray
        ``(2, >=2, h, w)``: per pattern, the band width at half height and the line
        interval of this frame and the one before.

    Returns
    -------
    numpy.ndarray
        ``(h, w)`` bool: in either pattern, both frames measured the cell and its band
        width or interval differ by more than :data:`MOVED_TOLERANCE_PX`.
    """
    with np.errstate(invalid="ignore"):
        moved = ((np.abs(grids[:, 0] - previous[:, 0]) > MOVED_TOLERANCE_PX)
                 | (np.abs(grids[:, 1] - previous[:, 1]) > MOVED_TOLERANCE_PX))  # fmt: skip
    return np.any(moved, axis=0)


class FlowModel:
    """Pattern geometry needed to turn band measurements into flows for one rig."""

    def __init__(self, rig: Rig):
        self.rig = rig
        self.single = rig.single_projector
        self.pairs = rig.patterns
        # the profile tables are loaded (or built once per machine, ~15 s) here, with
        # the depth LUT, not on the first frame of a live capture
        tables()
        #: per pattern, blur model (a, b): sigma^2 = a + b * magnification^2, measured
        #: once on static lines (the rig's ``blur``) or fitted on the moving bands
        self.blur = np.array([[1.0, 0.0], [1.0, 0.0]])
        self._fitted = False
        measured = [pat.blur for _, pat in rig.patterns]
        #: whether the rig file gives the blur (then it is never refitted)
        self.calibrated = all(b is not None for b in measured)
        #: relative error of the blur sigma that the uncertainty allows for
        self.blur_rel_error = CALIBRATED_BLUR_REL_ERROR if self.calibrated else BLUR_REL_ERROR
        #: where the blur model comes from: "rig", "still lines", "moving bands" or ""
        self.blur_source = "rig" if self.calibrated else ""
        self._prev: np.ndarray | None = None
        if self.calibrated:
            self.blur = np.array(measured, dtype=np.float64)
            self._fitted = True
        self._pool: list[list[np.ndarray]] = []
        self.frames = 0
        #: grid stride in camera pixels (set by the pipeline)
        self.stride = 1
        #: per pattern, the blur sigma (camera px) at the median magnification
        self.blur_px = [float("nan"), float("nan")]
        # per pattern: kind code, pitch (uniform) or exp2 step, projector width
        params = pattern_params(rig)
        self.kinds = params[:, 1].astype(np.int64)
        self.steps = params[:, 2].copy()
        self.widths = params[:, 3].copy()
        self.line_px = np.array([pat.width_px for _, pat in self.pairs])
        if not self.single and np.any(self.kinds != 0):
            raise ConfigError(
                "rig: projectors[].patterns[].kind: a two-projector rig needs uniform patterns "
                "(exp2 patterns are for the single-projector pair)"
            )
        # u from the interval ratio B2/B1 = P2(u)/P1(u) (single projector), on a uniform grid
        proj = rig.projectors[0]
        u = np.linspace(-0.5, proj.width - 0.5, 8192)
        if self.single:
            p1, p2 = (local_pitch(pat, proj.width, u) for _, pat in self.pairs)
            ratio = np.log(p2 / p1)
        else:
            ratio = np.linspace(0.0, 1.0, u.size)  # unused placeholder
        order = np.argsort(ratio)
        self._u_lo, self._u_hi = float(ratio[order][0]), float(ratio[order][-1])
        grid = np.linspace(self._u_lo, self._u_hi, 4096)
        self._u_of = np.interp(grid, ratio[order], u[order])
        self._u_step = (self._u_hi - self._u_lo) / (len(grid) - 1)

    def edge_model(self) -> np.ndarray:
        """Per pattern, the band detector's edge model (``edge`` of
        :func:`lightflow.app.core.bands.bands_in_row`): ``(line_px / pitch, a, b / pitch^2)``
        of the blur model, zeros before it is known or for exp2 patterns (no one pitch)."""
        out = np.zeros((2, 3))
        if self._fitted:
            for p in range(2):
                if self.kinds[p] == 0:
                    step = self.steps[p]
                    out[p] = (self.line_px[p] / step, self.blur[p, 0], self.blur[p, 1] / step**2)
        return out

    @property
    def fitted(self) -> bool:
        """Whether the blur model has been fitted from measured bands yet."""
        return self._fitted

    @property
    def blur_measured(self) -> bool:
        """Whether the blur was measured on still lines (the rig's, or a wall's between the
        first frames), not fitted on moving bands: then it is never refitted, and sweeps
        shorter than the line count."""
        return self.blur_source in ("rig", "still lines")

    def refits_at(self, frame: int, params) -> bool:
        """Whether :meth:`combine` may refit the blur model on its ``frame``-th call."""
        if self.blur_measured:
            return False
        return (not self._fitted or frame in BLUR_EARLY_REFITS
                or frame % params.blur_refit_frames == 0)  # fmt: skip

    def combine(self, grids: np.ndarray, params: FlowParams,
                periodic: np.ndarray | None = None) -> FlowMaps:  # fmt: skip
        """Per-pixel raw log ratio, the two flows in projector pixels, and their errors.

        Parameters
        ----------
        grids : numpy.ndarray
            ``(2, 4, h, w)``: per pattern, grid maps of the measured band width at
            half height ``m``, the line interval ``B``, the 50->20 % ramp ``r`` and the
            slant of the lines (columns per row).
        params : FlowParams
        periodic : numpy.ndarray, optional
            ``(2, h, w)`` bool: cells whose sweep was measured on the periodic profile of
            overlapping bands (:func:`lightflow.app.core.overlap.measure_runs`); they
            may fill the interval.

        Returns
        -------
        FlowMaps
        """
        f = self.frames
        # the optics do not change: refit on the pooled bands of the recent frames, often
        # while the pool fills (frames 0, 1, 2, 4, 8), then now and then
        if f in STILL_LINE_FRAMES and self._prev is not None and self.blur_source != "rig":
            self._blur_from_still_lines(grids)
        if not self.calibrated and f + 1 in STILL_LINE_FRAMES:
            self._prev = grids[:, :2].copy()
        if self.refits_at(f, params):
            self._refit_blur(grids)
        elif self.calibrated and f == 0:
            self._show_blur(self.magnifications(grids))
        self.frames += 1
        return self.recombine(grids, params, periodic)

    def reread(self, first: FlowMaps, grids: np.ndarray, fix: np.ndarray,
               params: FlowParams, periodic: np.ndarray | None = None,
               added: np.ndarray | None = None,
               fallback: np.ndarray | None = None) -> FlowMaps:  # fmt: skip
        """The flows of ``first`` read again with the line intervals corrected by ``fix``.

        ``fix`` is per pattern ``log(B_measured / B_predicted)`` (:mod:`.intervals`).
        The interval sets not only ``L / B`` but also the line's width in camera px
        (``B`` over the pitch), and a sweep shorter than the line is read against
        that width: an interval a few per cent short reads such a sweep long by
        about as much again times the line over the sweep (twice as much at half a
        line width).  So the sweeps are measured again with the predicted
        intervals.  Which cells move, and their expected error, stay those of
        ``first`` (the correction is smooth, not noise of the sweeps); where a sweep
        read again is no longer measurable, the first reading stands, its ``L / B``
        over the predicted interval.  ``periodic``: as for :meth:`combine`.

        ``added`` (bool per cell): cells whose bands ``grids`` has anew or changed
        besides their intervals (limb or steep bands that got one, :mod:`.arcs`); they are
        read again too, and one without a first reading takes the second whole (its
        causes and errors).  ``fallback``: per pattern, the whole change of the intervals
        since ``first`` (``log(old / new)``, ``fix`` included) when ``grids`` holds part
        of it already; a cell whose second reading fails keeps ``first`` scaled by it
        (by ``fix`` when None).
        """
        # a cell without a correction reads as before (the same inputs): not read again
        todo = (fix != 0).any(axis=0)
        fixed = None
        if todo.any():
            # only the intervals change: the other fields are read from ``grids`` (a copy
            # of them all cost 1.1 ms).  A view of a larger buffer, like ``grids[:, 1]``:
            # the kernels are compiled for one array layout
            fixed = np.empty((2, 2, *grids.shape[2:]))[:, 0]
            np.multiply(grids[:, 1], np.exp(-fix), out=fixed)
        if added is not None:
            todo |= added
        shift = fix if fallback is None else fallback
        # the choice between the readings is made where the second was read (elsewhere
        # it is the first, and so is the choice: its shift is 0 there)
        take = (shift, np.exp(shift), todo if added is None else added, added is not None)
        return self._read_again(grids, params, periodic, first, todo, fixed, take)

    def recombine(self, grids: np.ndarray, params: FlowParams,
                  periodic: np.ndarray | None = None, first: FlowMaps | None = None,
                  todo: np.ndarray | None = None,
                  intervals: np.ndarray | None = None) -> FlowMaps:  # fmt: skip
        """:meth:`combine` without touching the blur model (for :meth:`reread`).

        With ``first`` (a :class:`FlowMaps` of these cells, with its readings) and
        ``todo`` (bool per cell), only the cells in ``todo`` are read from ``grids``; the
        others keep their readings, and where no cell read again reaches, the decision
        of ``first``; the maps then come without readings (they are kept up to date only
        near ``todo``).  ``intervals`` (``(2, h, w)``, a view like ``grids[:, 1]``)
        replaces the line intervals of ``grids``.
        """
        if first is not None:
            return self._read_again(grids, params, periodic, first, todo, intervals)
        gh, gw = grids.shape[2:]
        sweeps = np.empty((2, gh, gw), np.float32)
        moving_at = np.empty((2, gh, gw), np.float32)
        pitch = np.ones((2, gh, gw), np.float32)
        sens = np.empty((2, gh, gw), np.float32)
        interval_ratio = np.empty((gh, gw), np.float32)
        banded = np.empty((gh, gw), np.float32)
        why = np.empty((gh, gw), np.uint8)
        todo = np.ones((gh, gw), np.bool_)
        if intervals is None:
            intervals = grids[:, 1]
        # bands of grid rows on a thread per core (the kernels release the GIL)
        run_rows(_sweeps, gh, *self._sweep_inputs(grids, intervals, params, periodic, todo),
                 sweeps, moving_at, pitch, interval_ratio, banded, sens, why)  # fmt: skip
        # what each cell read, before the decision below changes its cause
        read = (sweeps, moving_at, pitch, sens, interval_ratio, banded, why.copy())
        swept = np.isfinite(sweeps[0]) & np.isfinite(sweeps[1])
        # Average the sweeps themselves over a few cells before any decision or log:
        # a short sweep is noisy, and both thresholding it and taking its log bias it
        # (only the cells whose noise pushes them up would pass; E[log L] < log E[L]).
        # Both patterns, their common mask and their second moments in one blur.
        stack = np.empty((gh, gw, N_STACK_SINGLE if self.single else N_STACK), np.float32)
        busy = np.empty(gh, np.bool_)
        run_rows(_pack, gh, sweeps, banded, interval_ratio, self.single, stack, busy)
        sigma = params.sweep_smoothing_px / max(1, self.stride)
        blurred = _blur_busy(stack, sigma, busy)
        log_ratio = np.empty((gh, gw), np.float32)
        flows = np.empty((2, gh, gw), np.float32)
        lr_var = np.empty((gh, gw), np.float32)
        lr_sys = np.empty((gh, gw), np.float32)
        run_rows(_decide, gh, *self._decide_inputs(read, blurred, intervals, params), log_ratio,
                 flows, lr_var, lr_sys, why, 0, gw)  # fmt: skip
        return FlowMaps(log_ratio, [flows[0], flows[1]], list(self.blur_px), lr_var, lr_sys, why,
                        swept, read)  # fmt: skip

    def _sweep_inputs(self, grids, intervals, params, periodic, todo) -> tuple:
        """:func:`_sweeps`' arguments before its outputs."""
        tab = tables()
        if periodic is None:
            periodic = np.zeros((2, *grids.shape[2:]), np.bool_)
        measured = self.blur_measured
        return (
            grids, intervals, self.kinds, self.steps, self.widths, self.line_px, self.blur,
            self.single, self._u_lo, self._u_step, self._u_of, tab.joint, tab.inverse,
            S_AXIS[0], S_AXIS[1] - S_AXIS[0], W_STEP, M_STEP, R_STEP, L_AXIS[-1] - 1.0,
            params.measure_factor, params.measure_margin_px,
            params.calibrated_static_factor if measured else params.static_factor,
            params.calibrated_static_margin_px if measured else params.static_margin_px,
            self._fitted, self.blur_rel_error, self.still_depth(params), periodic, todo,
        )  # fmt: skip

    def _decide_inputs(self, read, blurred, intervals, params) -> tuple:
        """:func:`_decide`'s arguments before its outputs, for the readings ``read`` (as
        :attr:`FlowMaps.readings`) and the blurred stack."""
        sweeps, moving_at, pitch, sens, interval_ratio, _, _ = read
        sigma = params.sweep_smoothing_px / max(1, self.stride)
        # grid cells under the averaging kernel, times the stride: over the interval
        # (camera px) it is the number of independent bands averaged
        cells = 4.0 * math.pi * sigma * sigma * self.stride if sigma > 0 else self.stride
        return (sweeps, blurred, moving_at, pitch, interval_ratio, self.single,
                self.still_depth(params), params.sweep_outlier, params.measured_share, sens,
                intervals, cells)  # fmt: skip

    def _read_again(self, grids, params, periodic, first, todo, intervals, take=None):
        """:meth:`recombine` with ``first``; with ``take`` (:func:`_take_again`'s ``shift``,
        ``grow``, ``added`` and ``has_added``), :meth:`reread`'s choice between the two.

        Read again, a cell changes the blurred stack only within the kernel's reach (each
        cell of the blur is that of the whole map, see :func:`_gauss_window`): only the
        tiles of cells within that reach are decided again, in windows of whole tiles,
        and only the rows the windows' blurs read are read again and packed (where a
        board's outline was read again, 0.7 of 4.4 ms of CPU per frame).
        """
        gh, gw = grids.shape[2:]
        if intervals is None:
            intervals = grids[:, 1]
        sigma = params.sweep_smoothing_px / max(1, self.stride)
        # wide blurs are box passes, whose sums depend on where they start: all rows
        windowed = 0.0 < sigma <= ROW_BANDS_MAX_SIGMA
        reach = _halo(sigma) if windowed else max(gh, gw)
        windows = _reread_windows(todo, reach, threads())
        rows = np.zeros(gh, np.bool_)
        for r0, r1, _, _ in windows:
            rows[max(0, r0 - reach) : r1 + reach] = True
        read = tuple(np.empty_like(a) for a in first.readings)
        sweeps, moving_at, pitch, sens, interval_ratio, banded, read_why = read
        stack = np.empty((gh, gw, N_STACK_SINGLE if self.single else N_STACK), np.float32)
        busy = np.zeros(gh, np.bool_)
        inputs = self._sweep_inputs(grids, intervals, params, periodic, todo)

        def read_rows(r0, r1):
            for new, old in zip(read, first.readings, strict=True):
                new[..., r0:r1, :] = old[..., r0:r1, :]
            _sweeps(*inputs, sweeps, moving_at, pitch, interval_ratio, banded, sens, read_why,
                    r0, r1)  # fmt: skip
            _pack(sweeps, banded, interval_ratio, self.single, stack, busy, r0, r1)

        run_tasks(*(functools.partial(read_rows, r0, r1) for r0, r1 in _row_pieces(rows)))
        log_ratio = first.log_ratio.copy()
        flows = np.stack(first.flows)
        lr_var, lr_sys, why, swept = (a.copy() for a in (first.lr_var, first.lr_sys, first.why,
                                                         first.swept))  # fmt: skip
        whole = not windowed and windows  # one blur of all rows (box passes)
        blurred = _blur_busy(stack, sigma, busy) if whole else np.empty_like(stack)
        decide = self._decide_inputs(read, blurred, intervals, params)
        if take is not None:
            back = (first.log_ratio, np.stack(first.flows), first.lr_var, first.lr_sys, first.why,
                    *take, sweeps)  # fmt: skip

        def redo(r0, r1, c0, c1):
            if windowed:
                _gauss_window(stack, sigma, blurred, r0, r1, c0, c1)
            why[r0:r1, c0:c1] = read_why[r0:r1, c0:c1]
            _decide(*decide, log_ratio, flows, lr_var, lr_sys, why, c0, c1, r0, r1)
            if take is None:
                swept[r0:r1, c0:c1] = (np.isfinite(sweeps[0, r0:r1, c0:c1])
                                       & np.isfinite(sweeps[1, r0:r1, c0:c1]))  # fmt: skip
            else:
                _take_again(*back, log_ratio, flows, lr_var, lr_sys, why, swept, c0, c1, r0, r1)

        run_tasks(*(functools.partial(redo, *w) for w in windows))
        blur_px = list(self.blur_px) if take is None else first.blur_px
        return FlowMaps(log_ratio, [flows[0], flows[1]], blur_px, lr_var, lr_sys, why, swept)

    def replace_previous(self, grids: np.ndarray) -> None:
        """The previous frame's grids measured again (the camera's response changed):
        the still lines of the next :meth:`combine` are found against these."""
        if self._prev is not None:
            self._prev = grids[:, :2].copy()

    def still_depth(self, params: FlowParams) -> bool:
        """Whether lines that stand still get a depth (one projector, see ``static_depth``)."""
        return self.single and params.static_depth != "off"

    def magnifications(self, grids: np.ndarray) -> np.ndarray:
        """Per pattern and grid cell, camera px per projector px: the interval over the pitch.

        ``grids`` as in :meth:`combine`; one projector: the pitch at the column
        that the interval ratio of the two patterns gives.  NaN without intervals.
        """
        with np.errstate(invalid="ignore", divide="ignore"):
            B0, B1 = grids[0, 1], grids[1, 1]
            if self.single:
                u = np.interp(np.log(B1 / B0), np.linspace(self._u_lo, self._u_hi, len(self._u_of)),
                              self._u_of, left=np.nan, right=np.nan)  # fmt: skip
            out = np.empty((2, *B0.shape))
            for p, (proj, pat) in enumerate(self.pairs):
                P = local_pitch(pat, proj.width, u) if self.single else pat.pitch_px
                out[p] = grids[p, 1] / P
        return out

    def _blur_from_still_lines(self, grids: np.ndarray) -> None:
        """Measure the blur on lines that stood still since the previous frame (a wall).

        Their width is known from the rig, so their ramps give the blur
        (:func:`static_blur`), far better than the moving bands' fit.  Both
        patterns share one optics model, as in the fit; two patterns seen at
        different magnifications on one wall separate its camera and projector
        parts.  Used when enough lines stood still, over magnifications that
        differ by :data:`MIN_STILL_SPAN`; else the fit on moving bands stays.
        """
        samples = self.line_samples(grids)
        still = still_lines(grids, self._prev)
        samples[:, 0] = np.where(still.reshape(2, -1), samples[:, 0], np.nan)
        # both patterns pooled: one optics model
        m, r, line, scale, slant = samples.transpose(1, 0, 2).reshape(5, -1)
        fit = static_blur(m, r, line, scale, slant, min_bands=STILL_MIN_LINES)
        if fit is None:
            return
        seen = scale[np.isfinite(m) & (m < line + 1.0)]
        lo, hi = np.percentile(seen, [5, 95])
        if hi < MIN_STILL_SPAN * lo:
            return
        self.blur[:] = fit[:2]
        self._fitted = True
        self.blur_source = "still lines"
        self.blur_rel_error = CALIBRATED_BLUR_REL_ERROR
        self._show_blur(samples[:, 3])

    def line_samples(self, grids: np.ndarray) -> np.ndarray:
        """Per pattern, flat rows of what the blur is measured from, one column per cell.

        Returns
        -------
        numpy.ndarray
            ``(2, 5, h * w)``: the band width ``m``, the ramp, the line width and
            the magnification (:meth:`magnifications`), and the lines' slant.
        """
        mags = self.magnifications(grids)
        out = np.empty((2, 5, mags[0].size))
        for p, (_, pat) in enumerate(self.pairs):
            m, _, r, slant = grids[p]
            out[p] = np.stack([m, r, pat.width_px * mags[p], mags[p], slant]).reshape(5, -1)
        return out

    def _show_blur(self, mags: np.ndarray) -> None:
        """For display: each pattern's blur sigma at its median magnification ``mags[p]``."""
        for p in range(2):
            scale = mags[p][np.isfinite(mags[p])]
            med = float(np.median(scale)) if scale.size else 1.0
            self.blur_px[p] = float(np.sqrt(self.blur[p, 0] + self.blur[p, 1] * med**2))

    def _refit_blur(self, grids: np.ndarray) -> None:
        """Fit the blur model on a subsample of this frame's bands (both patterns at once)."""
        # every third cell suffices on a large object; a small one (a ball) needs them all
        k = 3 if np.count_nonzero(np.isfinite(grids[0, 0, ::3, ::3])) > 3000 else 1
        sub = grids[:, :, ::k, ::k]
        samples = self.line_samples(sub)
        with np.errstate(invalid="ignore", divide="ignore"):
            # only where the line spacing changes slowly (planes, gentle curves): on
            # strongly curved parts the edges also carry the change of magnification
            dB = np.abs(np.gradient(sub[:, 1], axis=2)) / (k * self.stride)
            samples[:, 0] = np.where(dB.reshape(2, -1) < 0.1, samples[:, 0], np.nan)
            # one optics model for both patterns, fitted on the moving bands of both: the
            # same camera, and the projectors' defocus scales with magnification alike
            sample = samples.transpose(1, 0, 2).reshape(5, -1)
            moving = np.isfinite(sample[0]) & (sample[0] > sample[2] + 1.0)
            # pool the moving bands of the recent frames: a small object (a ball) has too
            # few in one frame, and the fit of one frame is noisy (the optics do not change)
            self._pool.append([v[moving] for v in sample])
            self._pool = self._pool[-BLUR_POOL_FRAMES:]
            fitted = fit_blur(*(np.concatenate(v) for v in zip(*self._pool, strict=True)))
        if fitted is not None:
            self.blur[:] = BLUR_FIT_GAIN * np.asarray(fitted)
            self._fitted = True
            self.blur_source = "moving bands"
        self._show_blur(samples[:, 3])


#: :func:`_gauss` blurs bands of rows up to this sigma (each row as in one call)
ROW_BANDS_MAX_SIGMA = 3.0


def _halo(sigma: float) -> int:
    """Rows beyond a band of rows that :func:`_gauss` reads for it (OpenCV's kernel
    reaches 4 sigma)."""
    return int(4.0 * sigma) + 2


def _row_segments(rows: np.ndarray, reach: int) -> list:
    """The runs ``(r0, r1)`` of the rows within ``reach`` of a true one in ``rows`` (bool);
    None where they are more than half of them (then all rows at once, on every core)."""
    n = rows.size
    hit = np.flatnonzero(rows)
    step = np.zeros(n + 1, np.int64)
    np.add.at(step, np.maximum(hit - reach, 0), 1)
    np.add.at(step, np.minimum(hit + reach + 1, n), -1)
    covered = np.cumsum(step[:-1]) > 0
    if 2 * np.count_nonzero(covered) > n:
        return None
    edges = np.flatnonzero(np.diff(covered, prepend=False, append=False))
    return [(int(a), int(b)) for a, b in edges.reshape(-1, 2)]


def _row_pieces(rows: np.ndarray) -> list:
    """The runs ``(r0, r1)`` of true ``rows`` (bool), cut into pieces about as long as the
    rows over the threads (tasks for :func:`run_tasks`)."""
    edges = np.flatnonzero(np.diff(rows, prepend=False, append=False)).reshape(-1, 2)
    size = max(1, -(-int(np.count_nonzero(rows)) // threads()))
    return [(a, min(a + size, int(r1))) for r0, r1 in edges for a in range(int(r0), int(r1), size)]


def _tile_windows(tiles: np.ndarray, tile_rows: int, tile_cols: int) -> list:
    """Windows ``(r0, r1, c0, c1)`` (cells; they may end beyond the map) that cover the true
    ``tiles`` (bool, a tile per ``tile_rows`` x ``tile_cols`` cells): the runs along each
    row of tiles, joined down the rows while they span the same columns."""
    padded = np.zeros((tiles.shape[0], tiles.shape[1] + 2), np.int8)
    padded[:, 1:-1] = tiles
    ti, tj = np.nonzero(np.diff(padded, axis=1))  # a run's start, then its end
    out = []
    last = {}  # per span of columns, the window in ``out`` that has it last
    for k in range(0, ti.size, 2):
        i, c0, c1 = int(ti[k]), int(tj[k]), int(tj[k + 1])
        w = last.get((c0, c1))
        if w is not None and out[w][1] == i:
            out[w][1] = i + 1
        else:
            last[c0, c1] = len(out)
            out.append([i, i + 1, c0, c1])
    return [(r0 * tile_rows, r1 * tile_rows, c0 * tile_cols, c1 * tile_cols)
            for r0, r1, c0, c1 in out]  # fmt: skip


def warm_up_reread() -> None:
    """Compile (or load) the kernels of :meth:`FlowModel.reread`'s windows and of its choice
    between the readings, with a frame's argument types.

    Only a frame whose line intervals the arcs or the interval model correct reaches
    them, so a test image of straight stripes never does: on a cold start they compiled
    in the first frame.  :meth:`.pipeline.DepthPipeline.warm_up_optional` calls this; the demo calls
    it before it waits for its helper process.
    """
    todo = np.zeros((4, 4), np.bool_)
    todo[1, 1] = True
    _reread_windows(todo, 2, 2)

    def f32(*shape):
        return np.zeros(shape, np.float32)

    why = np.zeros((4, 4), np.uint8)
    _take_again(f32(4, 4), f32(2, 4, 4), f32(4, 4), f32(4, 4), why, f32(2, 4, 4), f32(2, 4, 4),
                todo, True, f32(2, 4, 4), f32(4, 4), f32(2, 4, 4), f32(4, 4), f32(4, 4),
                why.copy(), np.zeros((4, 4), np.bool_), 0, 4, 0, 4)  # fmt: skip


def _reread_windows(todo: np.ndarray, reach: int, parts: int) -> list:
    """Disjoint windows ``(r0, r1, c0, c1)`` that cover the cells within ``reach`` of a
    ``todo`` one (bool per cell), in whole tiles of :data:`REREAD_TILE`.

    Windows are joined where one costs less than two (:func:`_window_cost`; all cells if
    that costs less), then the dearest cut along their rows into tasks of about the
    cost of all over ``parts``.
    """
    gh, gw = todo.shape
    tiles = np.zeros((-(-gh // REREAD_TILE[0]), -(-gw // REREAD_TILE[1])), np.bool_)
    _dirty_tiles(todo, reach, *REREAD_TILE, tiles)
    win = np.array(_tile_windows(tiles, *REREAD_TILE), np.int64).reshape(-1, 4)
    np.minimum(win[:, 1], gh, out=win[:, 1])
    np.minimum(win[:, 3], gw, out=win[:, 3])
    win = _merge_windows(win, reach, gh, gw)
    costs = [_window_cost(*w, reach, gh, gw) for w in win]
    whole = _window_cost(0, gh, 0, gw, reach, gh, gw)
    if len(win) > 1 and sum(costs) >= whole:
        win, costs = np.array([[0, gh, 0, gw]]), [whole]
    share = sum(costs) / parts
    out = []
    for (r0, r1, c0, c1), cost in zip(win.tolist(), costs, strict=True):
        k = min(r1 - r0, max(1, round(cost / share)))
        edges = [r0 + (r1 - r0) * e // k for e in range(k + 1)]
        out += [(a, b, c0, c1) for a, b in zip(edges[:-1], edges[1:], strict=True)]
    return out


def _gauss(img: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur; wide ones as two box passes of equal variance (cost independent of sigma)."""
    if sigma <= ROW_BANDS_MAX_SIGMA:
        # bands of rows on a thread per core: each output pixel is the same weighted sum
        # of the same inputs (OpenCV's kernel reaches 4 sigma), so the values are those
        # of one call.  Not the box passes: their running sums depend on where they start
        out = np.empty_like(img)
        run_rows(_gauss_rows, img.shape[0], img, sigma, out)
        return out
    k = int(round(np.sqrt(6.0 * sigma * sigma + 1.0))) | 1  # var of 2 boxes: (k^2 - 1) / 6
    once = cv2.blur(img, (k, k), borderType=cv2.BORDER_REFLECT)
    return cv2.blur(once, (k, k), borderType=cv2.BORDER_REFLECT)


def _blur_busy(stack: np.ndarray, sigma: float, busy: np.ndarray) -> np.ndarray:
    """:func:`_gauss` of ``stack`` (``(h, w, c)``, 0 on the rows where ``busy`` is false).

    A small object (balls) leaves most rows without data: only the rows within the
    kernel's reach of one are blurred (each as in one call, see :func:`_gauss`), the
    others are 0 as the whole blur would make them (0 under the whole kernel).
    """
    if sigma <= 0:
        return stack
    near = _row_segments(busy, _halo(sigma)) if sigma <= ROW_BANDS_MAX_SIGMA else None
    if near is None:
        return _gauss(stack, sigma)
    blurred = np.zeros_like(stack)
    run_tasks(*(functools.partial(_gauss_rows, stack, sigma, blurred, r0, r1)
                for r0, r1 in near))  # fmt: skip
    return blurred


def _gauss_rows(img, sigma, out, r0, r1):
    """:func:`_gauss` (a Gaussian kernel) of ``img`` on rows ``r0 .. r1``, into ``out``."""
    _gauss_window(img, sigma, out, r0, r1, 0, img.shape[1])


def _gauss_window(img, sigma, out, r0, r1, c0, c1):
    """:func:`_gauss` (a Gaussian kernel) of ``img`` on rows ``r0 .. r1`` and columns ``c0 ..
    c1``, into ``out``.

    Each cell is the same weighted sum of the same inputs as in one call on the whole
    map: the window read reaches the kernel's halo beyond, and OpenCV filters a row in
    vectors of up to :data:`SIMD_COLUMNS` values from its first, the last few on their
    own (rounded otherwise).  So the window read starts on a multiple of
    :data:`SIMD_COLUMNS` columns and ends on one after it (no last few), or at the
    map's last column (the same last few as the whole map's).
    """
    halo = _halo(sigma)
    h, w = img.shape[:2]
    lo, hi = max(0, r0 - halo), min(h, r1 + halo)
    a = max(0, c0 - halo) // SIMD_COLUMNS * SIMD_COLUMNS
    b = a + -(-(c1 + halo - a) // SIMD_COLUMNS) * SIMD_COLUMNS
    if b >= w or c1 + halo >= w:
        b = w
    band = cv2.GaussianBlur(img[lo:hi, a:b], (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    out[r0:r1, c0:c1] = band[r0 - lo : r1 - lo, c0 - a : c1 - a]


def _masked_smooth(values, variance, keep, sigma, fill_fraction):
    """Masked smoothing of the float32 ``(h, w)`` map ``values`` over the pixels ``keep``.

    With ``variance`` (or None), ``values`` is an inverse-variance weighted mean and
    the variance a plain mean over the same pixels; returns the list of the smoothed
    maps (``[values]`` or ``[values, variance]``).
    """
    has_var = variance is not None
    # what is blurred, in one pass: the mask, then the weights, the weighted values and
    # the variance (with ``variance``) or the values, each 0 outside the mask
    inputs = [np.empty(values.shape, np.float32) for _ in range(4 if has_var else 2)]
    if has_var:
        _smooth_inputs(values, variance, True, keep, *inputs)
    else:
        _smooth_inputs(values, values, False, keep, inputs[0], inputs[0], inputs[1], inputs[1])
    # one blur per plane: OpenCV's 4-channel float box filter ran 4-9x slower on
    # these maps than four planes (2.6 against 1.2 ms at 300x400); they are
    # independent, so they run at once, one per core
    blurred = run_tasks(*(functools.partial(_gauss, x, sigma) for x in inputs))
    if fill_fraction < 1.0:
        # only holes are filled: data on both sides (left and right, or above and
        # below) within the kernel.  Beside a convex edge (a blade, a ball's limb)
        # a third of the kernel is valid too, and filling there grew the object.
        # More than half the kernel valid is inside a straight edge, never beyond it.
        enclosed = _enclosed(keep, int(2.0 * sigma) + 1)
    else:
        enclosed = keep  # unused
    if has_var:
        den, wden, num, var_num = blurred
    else:
        den, num = blurred
        wden = var_num = den  # unused
    # NaN outside what is filled (no division by 0), then the means, in place
    _smooth_outputs(den, wden, num, var_num, keep, enclosed, has_var, fill_fraction < 1.0,
                    np.float32(fill_fraction))  # fmt: skip
    return [num, var_num] if has_var else [num]


# The kernels below fuse what were numpy passes over the map (a temporary each); each
# pixel gets the same float32 operations, so the values are those of the numpy code.


@nb.njit(cache=True, error_model="numpy", nogil=True, **NO_CFUNC)
def _outlier_inputs(values, variance, has_var, mask, masked, ones):
    """``mask``: ``values`` (and ``variance``) finite; ``masked``: ``values`` there, else 0;
    ``ones``: ``mask`` as 1.0 / 0.0."""
    h, w = values.shape
    for i in range(h):
        for j in range(w):
            ok = np.isfinite(values[i, j]) and (not has_var or np.isfinite(variance[i, j]))
            mask[i, j] = ok
            masked[i, j] = values[i, j] if ok else np.float32(0.0)
            ones[i, j] = np.float32(1.0) if ok else np.float32(0.0)


@nb.njit(cache=True, error_model="numpy", nogil=True, **NO_CFUNC)
def _residuals(values, mask, num, den, resid):
    """``resid``: ``|values - num / den|`` on ``mask``, NaN elsewhere."""
    h, w = values.shape
    for i in range(h):
        for j in range(w):
            resid[i, j] = abs(values[i, j] - num[i, j] / den[i, j]) if mask[i, j] else np.nan


@nb.njit(cache=True, error_model="numpy", nogil=True, **NO_CFUNC)
def _keep_inliers(resid, limit, keep):
    """``keep``: ``resid <= limit`` (float32; false where ``resid`` is NaN)."""
    h, w = resid.shape
    for i in range(h):
        for j in range(w):
            keep[i, j] = resid[i, j] <= limit


@nb.njit(cache=True, error_model="numpy", nogil=True, **NO_CFUNC)
def _smooth_inputs(values, variance, has_var, keep, ones, wt, masked, var_masked):
    """On ``keep``, else 0: ``ones`` 1.0; ``masked`` the ``values``; with ``has_var``, ``wt``
    the inverse ``variance``, ``masked`` the values times it and ``var_masked`` the variance
    (without, ``wt`` and ``var_masked`` are not written)."""
    h, w = values.shape
    zero = np.float32(0.0)
    for i in range(h):
        for j in range(w):
            k = keep[i, j]
            ones[i, j] = np.float32(1.0) if k else zero
            if has_var:
                inv = np.float32(1.0) / max(variance[i, j], np.float32(1e-12))
                wt[i, j] = inv if k else zero
                masked[i, j] = values[i, j] * inv if k else zero
                var_masked[i, j] = variance[i, j] if k else zero
            else:
                masked[i, j] = values[i, j] if k else zero


@nb.njit(cache=True, error_model="numpy", nogil=True, **NO_CFUNC)
def _smooth_outputs(den, wden, num, var_num, keep, enclosed, has_var, holes, fill_fraction):
    """In place: ``num`` over ``wden`` (with ``has_var``, and ``var_num`` over ``den``) or
    over ``den``, where the pixel is kept or filled, else NaN (also in ``den``, ``wden``)."""
    h, w = den.shape
    for i in range(h):
        for j in range(w):
            d = den[i, j]
            fill = d >= fill_fraction
            if holes:
                fill = fill and (enclosed[i, j] or d > 0.5)
            if not (fill or keep[i, j]):
                den[i, j] = np.nan
                if has_var:
                    wden[i, j] = np.nan
            if has_var:
                num[i, j] /= wden[i, j]
                var_num[i, j] /= den[i, j]
            else:
                num[i, j] /= den[i, j]


def _enclosed(mask: np.ndarray, r: int) -> np.ndarray:
    """Pixels with a ``mask`` pixel within ``r`` on both sides along a row or a column."""
    m = mask.view(np.uint8)  # 0 or 1
    row = np.ones((1, r + 1), np.uint8)
    col = np.ones((r + 1, 1), np.uint8)
    # one-sided dilations: the anchor at one end of the kernel looks only one way
    left = cv2.dilate(m, row, anchor=(r, 0))
    right = cv2.dilate(m, row, anchor=(0, 0))
    up = cv2.dilate(m, col, anchor=(0, r))
    down = cv2.dilate(m, col, anchor=(0, 0))
    left &= right
    up &= down
    left |= up
    return left.view(bool)


def smooth_log_ratio(
    log_ratio: np.ndarray, sigma: float, outlier_sigmas: float, fill_fraction: float = 1.0,
    variance: np.ndarray | None = None,
):  # fmt: skip
    """Robust masked smoothing: drop outliers against a first smoothing, then smooth again.

    Parameters
    ----------
    log_ratio : numpy.ndarray
        ``(h, w)`` map, NaN without a value.
    sigma, outlier_sigmas, fill_fraction : float
        Gaussian sigma (grid px), outlier threshold in robust deviations, and
        the share of valid kernel weight that fills a hole inside the surface.
    variance : numpy.ndarray, optional
        A per-pixel variance: the log ratio becomes an inverse-variance weighted
        mean (a pixel predicted twice as noisy counts a quarter), and the
        variance itself is averaged over the same pixels and kernel.

    Returns
    -------
    numpy.ndarray, or (numpy.ndarray, numpy.ndarray) with ``variance``
    """
    values = log_ratio.astype(np.float32, copy=False)
    var = None if variance is None else variance.astype(np.float32, copy=False)
    shape = values.shape
    mask = np.empty(shape, np.bool_)
    masked = np.empty(shape, np.float32)
    ones = np.empty(shape, np.float32)
    _outlier_inputs(values, values if var is None else var, var is not None, mask, masked,
                    ones)  # fmt: skip
    if sigma <= 0:
        out = [np.where(mask, v, np.float32(np.nan)) for v in (values, var) if v is not None]
        return out[0] if variance is None else tuple(out)
    keep = mask
    if outlier_sigmas > 0:
        # a rough local mean is enough to spot outliers: a box filter costs less
        k = 2 * int(round(sigma)) + 1
        num, den = run_tasks(functools.partial(cv2.blur, masked, (k, k)),
                             functools.partial(cv2.blur, ones, (k, k)))  # fmt: skip
        resid = masked  # no longer needed: reused
        _residuals(values, mask, num, den, resid)
        sample = resid[::2, ::2]  # the spread of the residuals, from a quarter of them
        finite = sample[np.isfinite(sample)]
        if finite.size >= 16:
            mad = float(np.median(finite)) * 1.4826 + 1e-6
            # a NaN residual (no data, or none around) compares false: those are the NaN
            # pixels; the limit in float32, as numpy compares a float32 map with it
            keep = np.empty(shape, np.bool_)
            _keep_inliers(resid, np.float32(outlier_sigmas * mad), keep)
    # outliers are replaced by their neighbourhood, pixels without data only inside
    out = _masked_smooth(values, var, keep, sigma, fill_fraction)
    return out[0] if variance is None else tuple(out)
