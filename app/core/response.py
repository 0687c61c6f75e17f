"""The camera's response curve: undo it before any band is measured.

The band model (line box, motion box, blur) adds light, so it holds for a
camera whose values are proportional to the light.  Many cameras (webcams,
machine-vision cameras with gamma on, renderers writing sRGB) store
``DN = full * (light / full) ** (1 / gamma)`` instead.  Measured in those
values a band's half-height lies lower on its edges: every band reads wider,
short sweeps most, and the depth is biased long by tens of millimetres.

:func:`linearise` maps each value back through a table; :func:`estimate_gamma`
finds ``gamma`` from the frames themselves, from the shape of band edges: in
linear values the two halves of a swept line's edge are point-symmetric about
its half height (a box convolved with a box and a symmetric blur), while a
response curve stretches the lower half and squeezes the upper one.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from . import bands as bd
from .rig import GAMMA_RANGE
from .threads import run_rows

__all__ = [
    "GAMMA_RANGE",
    "LINEAR_FULL",
    "edge_asymmetry",
    "estimate_gamma",
    "linearise",
    "linearising_table",
]
#: full scale of a linearised image (uint16)
LINEAR_FULL = 65535.0


def linearising_table(gamma: float, dtype: np.dtype, full_scale: float) -> np.ndarray:
    """The uint16 linear value of every camera value: ``65535 * (v / full) ** gamma``.

    Parameters
    ----------
    gamma : float
        The camera's gamma (1: linear).
    dtype : numpy.dtype
        uint8 or uint16: the camera image's type.
    full_scale : float
        The camera's full-scale value (255, 4095 for 12 bits, 65535).

    Returns
    -------
    numpy.ndarray
        ``(256,)`` or ``(65536,)`` uint16 table.
    """
    n = 256 if np.dtype(dtype) == np.uint8 else 65536
    v = np.minimum(np.arange(n, dtype=np.float64) / full_scale, 1.0)
    return np.round(LINEAR_FULL * v**gamma).astype(np.uint16)


def linearise(image: np.ndarray, table: np.ndarray) -> np.ndarray:
    """``table[image]``: a uint16 image of the same shape, in linear values.

    Parameters
    ----------
    image : numpy.ndarray
        ``(h, w, c)`` uint8 or uint16 camera image.
    table : numpy.ndarray
        From :func:`linearising_table` for this image's type.

    Returns
    -------
    numpy.ndarray
        uint16, full scale :data:`LINEAR_FULL`.
    """
    flat = np.ascontiguousarray(image).reshape(image.shape[0], -1)
    out = np.empty(flat.shape, np.uint16)
    run_rows(_apply_table, flat.shape[0], flat, table, out)
    return out.reshape(image.shape)


@nb.njit(cache=True, nogil=True)
def _apply_table(flat, table, out, r0, r1):
    for i in range(r0, r1):
        src = flat[i]
        dst = out[i]
        for j in range(src.shape[0]):
            dst[j] = table[src[j]]


# ----------------------------------------------------------------------------- estimate

#: band edges needed for an estimate (a frame of a board gives thousands)
MIN_EDGES = 200
#: an estimate this close to 1 is a linear camera (the estimate's spread on linear
#: renders is well inside it), so linear cameras keep exactly their values
LINEAR_SNAP = 0.12
#: a band is measured when its half-height length is this many of its 50->20 % ramps:
#: then its two edges are apart, and each is point-symmetric about its half height
MIN_LENGTH_RAMPS = 8.0


@nb.njit(cache=True)
def _cross(x, j, level, step):
    """From sample ``j`` (at or above ``level``), walking by ``step`` (+1 or -1): where
    ``x`` first falls below ``level``, linearly interpolated; NaN at the row's end."""
    n = x.shape[0]
    while 0 <= j + step < n and x[j + step] >= level:
        j += step
    if not 0 <= j + step < n:
        return np.nan
    a = x[j + step]
    b = x[j]
    if not b > a:
        return np.nan
    return j + step * (b - level) / (b - a)


@nb.njit(cache=True)
def _asymmetries(rows, wins, gamma, min_contrast, out):
    """Write the edge asymmetries of ``rows`` raised to ``gamma`` into ``out``; their count.

    ``rows``: ``(n, w)`` camera values over full scale (0..1), one pattern's channel
    per row; ``wins[i]``: the detector's window for row ``i``.  An edge's asymmetry is
    ``((x50 - x20) - (x80 - x50)) / (x80 - x20)``, from its crossings of 20, 50 and
    80 % of the band's height: 0 when the values are linear in the light.
    """
    n, w = rows.shape
    lin = np.empty(w)
    thr = np.empty((2, w))
    found = np.empty((bd.MAX_LEAK_BANDS, bd.N_FIELDS))
    c = np.empty(3)
    m = 0
    for i in range(n):
        for j in range(w):
            lin[j] = rows[i, j] ** gamma
        bd.sliding_mid(lin, wins[i], thr)
        nb_ = bd.bands_in_row(lin, thr, min_contrast, 0.3, 1.0, 0.25, found)
        for k in range(nb_):
            if found[k, bd.F_VALID] <= 0.0:
                continue
            xl = found[k, bd.F_START]
            xr = found[k, bd.F_END]
            ramp = found[k, bd.F_RAMP]
            height = found[k, bd.F_HEIGHT]
            if not (xr - xl >= MIN_LENGTH_RAMPS * ramp and height > 0.0):
                continue
            # the plateau as the detector takes it: the mean over the band's middle half
            p0 = int(np.ceil(xl + 0.25 * (xr - xl)))
            p1 = int(np.floor(xr - 0.25 * (xr - xl)))
            if p1 < p0:
                continue
            top = 0.0
            for j in range(p0, p1 + 1):
                top += lin[j]
            top /= p1 - p0 + 1
            bg = top - height
            for side in range(2):
                step = -1 if side == 0 else 1
                start = p0 if side == 0 else p1
                for q in range(3):
                    c[q] = _cross(lin, start, bg + (0.8, 0.5, 0.2)[q] * height, step)
                span = abs(c[2] - c[0])
                if not span > 0.5 or m >= out.shape[0]:  # also NaN
                    continue
                out[m] = (abs(c[1] - c[2]) - abs(c[0] - c[1])) / span
                m += 1
    return m


def edge_asymmetry(rows: np.ndarray, wins: np.ndarray, gamma: float,
                   min_contrast: float = 0.025) -> tuple[float, int]:  # fmt: skip
    """Median asymmetry of the band edges in ``rows`` linearised with ``gamma``, and their count.

    Only bands whose half-height length is :data:`MIN_LENGTH_RAMPS` ramps or more
    count: their two edges are apart, so each is point-symmetric about its half
    height in linear values, whatever the line width, sweep and blur.

    Parameters
    ----------
    rows : numpy.ndarray
        ``(n, w)`` float64 camera values over full scale, one pattern channel per row.
    wins : numpy.ndarray
        ``(n,)`` int64: the band detector's window per row (about two line intervals).
    gamma : float
        Candidate response.
    min_contrast : float
        Faintest band, over full scale, in linear values.

    Returns
    -------
    (float, int)
        NaN without edges.
    """
    out = np.empty(rows.shape[0] * 2 * bd.MAX_LEAK_BANDS)
    n = _asymmetries(rows, wins, gamma, min_contrast, out)
    return (float(np.median(out[:n])) if n else float("nan")), n


def estimate_gamma(rows: np.ndarray, wins: np.ndarray, min_edges: int = MIN_EDGES):
    """The camera's gamma from the shape of its band edges; None when they are too few.

    The edges' median asymmetry rises through 0 at the camera's gamma: candidates
    below it leave the lower half of each edge longer, candidates above it the
    upper half.  Far above it the bands grow faint and few and the asymmetry falls
    back, so the root is the first rise through 0 on a grid of candidates
    (log-spaced over :data:`GAMMA_RANGE`), refined by bisection.  Within
    :data:`LINEAR_SNAP` of 1 the camera is linear.

    Parameters
    ----------
    rows, wins : numpy.ndarray
        As for :func:`edge_asymmetry`: rows of raw pattern channels over full scale.
    min_edges : int
        Edges needed on both sides of the root.

    Returns
    -------
    float or None
    """
    grid = np.linspace(np.log(GAMMA_RANGE[0]), np.log(GAMMA_RANGE[1]), 28)
    prev = None
    for g in grid:
        a, n = edge_asymmetry(rows, wins, float(np.exp(g)))
        ok = n >= min_edges and np.isfinite(a)
        if ok and prev is not None and prev[1] < 0.0 <= a:
            lo, hi = prev[0], g
            break
        prev = (g, a) if ok else None
    else:
        return None
    for _ in range(8):  # to within 0.1 % in gamma
        mid = 0.5 * (lo + hi)
        a, n = edge_asymmetry(rows, wins, float(np.exp(mid)))
        if n < min_edges or not np.isfinite(a):
            break
        if a < 0.0:
            lo = mid
        else:
            hi = mid
    gamma = float(np.exp(0.5 * (lo + hi)))
    return 1.0 if abs(gamma - 1.0) < LINEAR_SNAP else gamma
