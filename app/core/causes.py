"""Why a pixel got no depth: one cause per analysis-grid pixel, counted per frame.

Every grid pixel ends as exactly one of :data:`CAUSES`: ``depth`` or the first
reason, in pipeline order, that kept it from a depth.  Band-level reasons come
from the band detector (``F_VALID`` codes of :mod:`lightflow.app.core.bands`) through
the band nearest to the pixel along its row; the flow stage adds its own.
"""

from __future__ import annotations

import cv2
import numba as nb
import numpy as np

from .bands import (
    BAND_CUT,
    BAND_FAINT,
    BAND_IRREGULAR,
    BAND_LIMB,
    BAND_OVERLAP,
    BAND_STEEP,
    F_END,
    F_RAMP,
    F_START,
    F_VALID,
    value_counts,
)
from .kernel_options import INTERNAL, NO_CFUNC
from .threads import run_rows

DEPTH = 0
NO_LINES = 1
FAINT = 2
CUT = 3
OVERLAP = 4
IRREGULAR = 5
STATIC = 6
MODEL_RANGE = 7
BLUR_UNKNOWN = 8
INCONSISTENT = 9
UNCERTAIN = 10
DEPTH_RANGE = 11
LONE = 12

#: fewest of a depth's 8 neighbouring cells that must have a depth too (see :func:`lone_cells`)
MIN_NEIGHBOURS = 4

#: (name, what it means) per cause code, in code order
CAUSES = (
    ("depth", "got a depth"),
    ("no lines", "no projected line near it in one pattern: shadow, a dark surface, or "
                 "outside a projector"),
    ("faint", "the band's contrast is below the detector's minimum (2 % of full scale)"),
    ("cut", "the band is cut by an object edge or the image border"),
    ("overlap", "bands merge: the sweep fills the line interval (a shorter exposure helps)"),
    ("irregular", "print or an edge inside the band, or line intervals that disagree"),
    ("static", "no measurable sweep: the surface does not move (or too little)"),
    ("out of model range", "band or line wider than the profile tables"),
    ("blur not fitted", "a short sweep before the blur model has been fitted"),
    ("inconsistent", "the sweep disagrees with the sweeps around it"),
    ("uncertain", "the predicted depth error is too large (over max_depth_std of the depth)"),
    ("out of depth range", "the flow ratio lies outside the rig's working range"),
    ("lone", "fewer than half of the cells around it have a depth: a stray measurement"),
)  # fmt: skip
CAUSE_NAMES = tuple(name for name, _ in CAUSES)
#: RGB colour of each cause, as the Rerun view and `lightflow eval --pictures` draw it
#: (code order: depth, no lines, faint, cut, overlap,
#: irregular, static, out of model range, blur not fitted, inconsistent, uncertain,
#: out of depth range, lone)
CAUSE_COLOURS = ((0, 200, 0), (40, 40, 40), (120, 120, 200), (230, 120, 30), (200, 0, 200),
                 (230, 200, 0), (90, 90, 90), (255, 0, 0), (0, 200, 200), (160, 60, 0),
                 (255, 130, 180), (255, 255, 255), (0, 110, 255))  # fmt: skip



@nb.njit(cache=True, error_model="numpy", **INTERNAL)
def _band_code_cause(code):
    if code == BAND_FAINT:
        return FAINT
    if code == BAND_CUT:
        return CUT
    if code == BAND_OVERLAP:
        return OVERLAP
    if code == BAND_IRREGULAR or code == BAND_LIMB or code == BAND_STEEP:
        return IRREGULAR
    return FAINT  # segments never measured are faint ones


def band_causes(bands, counts, k, stride, gw, reach, out):
    """Per grid cell, the cause code of the band nearest along its row (``DEPTH`` if valid).

    Parameters
    ----------
    bands, counts : numpy.ndarray
        One pattern's detector output, ``k`` measured rows per grid row.
    stride : int
        Grid stride (camera px).
    gw : int
        Grid width.
    reach : float
        Farthest distance (camera px) from a band's support at which it still
        speaks for a cell; beyond it the cell has ``NO_LINES``.
    out : numpy.ndarray
        ``(gh, gw)`` uint8 output.
    """
    # rows of cells on a thread per core (the kernel releases the GIL)
    run_rows(_band_causes, out.shape[0], bands, counts, k, stride, gw, reach, out)


@nb.njit(cache=True, error_model="numpy", nogil=True, **NO_CFUNC)
def _band_causes(bands, counts, k, stride, gw, reach, out, i0, i1):
    """:func:`band_causes` on the grid rows ``i0 .. i1``."""
    off = 0.5 * (stride - 1)
    for i in range(i0, i1):
        r = i * k
        n = counts[r]
        if n == 0:
            for j in range(gw):
                out[i, j] = NO_LINES
            continue
        # the supports of the nearest band so far and of the next one, read once per band
        q = 0
        a, b = _support(bands, r, 0)
        a1, b1 = _support(bands, r, 1) if n > 1 else (0.0, 0.0)
        for j in range(gw):
            x = j * stride + off
            # bands are in column order: advance while the next one is nearer (each
            # distance computed once per cell)
            d = _distance(a, b, x)
            while q + 1 < n:
                d1 = _distance(a1, b1, x)
                if d1 > d:
                    break
                q += 1
                a, b = a1, b1
                d = d1
                if q + 1 < n:
                    a1, b1 = _support(bands, r, q + 1)
            if d > reach:
                out[i, j] = NO_LINES
            elif bands[r, q, F_VALID] > 0:
                out[i, j] = DEPTH
            else:
                out[i, j] = _band_code_cause(bands[r, q, F_VALID])


def merge_causes(per_pattern, intervals, why, log_ratio, depth, out):
    """One cause per grid cell from the patterns' band causes and the flow stage's.

    A cell with a depth has ``DEPTH``; else ``NO_LINES`` when a pattern has no line
    near it; else the first pattern's band cause, then the second's, then the flow
    stage's ``why``; a cell left with ``DEPTH`` then lost it in the smoothing
    (``INCONSISTENT``: no log ratio) or in the depth table (``DEPTH_RANGE``).  One pass
    over the grid (the numpy expressions it replaces cost a temporary each).

    Parameters
    ----------
    per_pattern : numpy.ndarray
        ``(2, h, w)`` uint8 :func:`band_causes` of each pattern.
    intervals : numpy.ndarray
        ``(2, h, w)`` line intervals on the grid: a finite one means valid bands around
        the cell (the band stage let it through, ``DEPTH``).
    why : numpy.ndarray
        ``(h, w)`` uint8 cause of the flow stage.
    log_ratio, depth : numpy.ndarray
        ``(h, w)`` smoothed log flow ratio and depth (NaN: none).
    out : numpy.ndarray
        ``(h, w)`` uint8 output.
    """
    # rows of cells on a thread per core (the kernel releases the GIL)
    run_rows(_merge_causes, out.shape[0], per_pattern, intervals, why, log_ratio, depth, out)


@nb.njit(cache=True, error_model="numpy", nogil=True, **NO_CFUNC)
def _merge_causes(per_pattern, intervals, why, log_ratio, depth, out, i0, i1):
    """:func:`merge_causes` on the grid rows ``i0 .. i1``."""
    gw = out.shape[1]
    for i in range(i0, i1):
        for j in range(gw):
            if np.isfinite(depth[i, j]):
                out[i, j] = DEPTH  # holes filled by the smoothing too, whatever their cause
                continue
            c0 = DEPTH if np.isfinite(intervals[0, i, j]) else per_pattern[0, i, j]
            c1 = DEPTH if np.isfinite(intervals[1, i, j]) else per_pattern[1, i, j]
            if c0 == NO_LINES or c1 == NO_LINES:
                out[i, j] = NO_LINES
                continue
            c = c0 if c0 != DEPTH else c1 if c1 != DEPTH else why[i, j]
            if c == DEPTH:
                # dropped by the robust smoothing, or a ratio outside the working range
                c = INCONSISTENT if not np.isfinite(log_ratio[i, j]) else DEPTH_RANGE
            out[i, j] = c


@nb.njit(cache=True, error_model="numpy", inline="always", **NO_CFUNC)
def _support(bands, r, q):
    """First and last column of band ``q`` of row ``r``'s support: its extent and two
    ramps on each side."""
    ramp = bands[r, q, F_RAMP] if bands[r, q, F_RAMP] > 0 else 0.0
    return bands[r, q, F_START] - 2.0 * ramp, bands[r, q, F_END] + 2.0 * ramp


@nb.njit(cache=True, error_model="numpy", inline="always", **NO_CFUNC)
def _distance(a, b, x):
    """Distance from column ``x`` to the support ``a .. b`` (0 inside)."""
    if x < a:
        return a - x
    if x > b:
        return x - b
    return 0.0


def lone_cells(depth: np.ndarray) -> np.ndarray:
    """The grid cells whose depth fewer than :data:`MIN_NEIGHBOURS` of their 8 neighbours share.

    A surface's depth covers neighbouring cells; a lone cell, or a strip one row tall, is
    a stray measurement (on a static wall: still lines whose widths noise pushed over a
    moving line's), and showed as stray points in the 3D view.

    Parameters
    ----------
    depth : numpy.ndarray
        ``(h, w)`` depth on the analysis grid, NaN where none.

    Returns
    -------
    numpy.ndarray
        ``(h, w)`` bool: cells with a depth and too few neighbours with one.
    """
    valid = np.isfinite(depth).astype(np.float32)
    around = cv2.boxFilter(valid, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
    return (valid > 0) & (around - valid < MIN_NEIGHBOURS - 0.5)


def count_causes(causes: np.ndarray, where: np.ndarray | None = None) -> np.ndarray:
    """Pixels per cause code (``len(CAUSES)`` counts), optionally only ``where`` is true."""
    values = causes if where is None else causes[where]
    counts = value_counts(values)
    if counts.size < len(CAUSES):
        counts = np.pad(counts, (0, len(CAUSES) - counts.size))
    return counts[: len(CAUSES)]


def describe_counts(counts, of: int | None = None, top: int = 4) -> str:
    """``"static 41 %, no lines 30 %, ..."``: the largest causes of no depth, in % of ``of``."""
    total = of if of is not None else int(np.sum(counts))
    if total <= 0:
        return "no pixels"
    order = [c for c in np.argsort(counts[1:])[::-1] + 1 if counts[c] > 0][:top]
    if not order:
        return "none"
    return ", ".join(f"{CAUSE_NAMES[c]} {100.0 * counts[c] / total:.0f} %" for c in order)
