"""The camera's response curve: undo it before any band is measured.

The band model (line box, motion box, blur) adds light, so it holds for a
camera whose values are proportional to the light.  Many cameras (webcams,
machine-vision cameras with gamma on, renderers writing sRGB) store
``DN = full * (light / full) ** (1 / gamma)`` instead.  Measured in those
values a band's half-height lies lower on its edges: every band reads wider,
short sweeps most, and the depth is biased long by tens of millimetres.

:func:`linearise` maps each value back through a table; :func:`find_gamma`
finds ``gamma`` on lines that stand still: their ramps give their blur, their
width (known from the rig) and that blur give their width at half height
(the band model), and a camera that is not linear reads them wider.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from .kernel_options import NO_CFUNC
from .rig import GAMMA_RANGE
from .threads import run_rows

__all__ = ["GAMMA_RANGE", "LINEAR_FULL", "LINEAR_SNAP", "MIN_STILL_LINES", "find_gamma",
           "linearise", "linearising_table"]

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


@nb.njit(cache=True, nogil=True, **NO_CFUNC)
def _apply_table(flat, table, out, r0, r1):
    for i in range(r0, r1):
        src = flat[i]
        dst = out[i]
        for j in range(src.shape[0]):
            dst[j] = table[src[j]]


# ----------------------------------------------------------------------------- measure

#: a measured gamma this close to 1 is a linear camera (linear renders of the tuning rigs
#: measure 1.00-1.02), so a linear camera keeps exactly its values and its speed
LINEAR_SNAP = 0.05
#: still lines (grid cells) needed to measure the response on
MIN_STILL_LINES = 500


def find_gamma(excess, min_lines: int):
    """The gamma at which still lines are as wide as the band model says.

    ``excess(log_gamma)`` is the median excess width of the still lines
    linearised with that gamma (:func:`lightflow.app.core.profile_model.
    static_width_excess`) and how many lines it is over, or None when too few
    lines are left.  It falls as the gamma rises (too small a gamma leaves the
    lines wide).  When it falls through 0 between the bounds of
    :data:`LINEAR_SNAP` the camera is linear (two candidates); else a grid of
    candidates, log-spaced over :data:`GAMMA_RANGE`, brackets its fall through
    0, and bisection refines it.

    Parameters
    ----------
    excess : callable
        ``excess(log_gamma) -> (float, int) or None``.
    min_lines : int
        Lines needed at the answer.

    Returns
    -------
    (float, float, int) or None
        The gamma (exactly 1 within :data:`LINEAR_SNAP` of it), the measurement
        before that snap, and the lines at the answer; None when no candidate
        brackets the root.
    """
    # most cameras are linear: two candidates at the snap's bounds settle that at once
    lo, hi = np.log(1.0 - LINEAR_SNAP), np.log(1.0 + LINEAR_SNAP)
    e_lo, e_hi = excess(float(lo)), excess(float(hi))
    if (e_lo is not None and e_hi is not None and min(e_lo[1], e_hi[1]) >= min_lines
            and e_lo[0] > 0.0 >= e_hi[0]):  # fmt: skip
        at = lo + (hi - lo) * e_lo[0] / (e_lo[0] - e_hi[0])  # the root, interpolated
        return 1.0, float(np.exp(at)), e_hi[1]
    grid = np.linspace(np.log(GAMMA_RANGE[0]), np.log(GAMMA_RANGE[1]), 13)
    prev = None
    for g in grid:
        e = excess(float(g))
        ok = e is not None and e[1] >= min_lines
        if ok and prev is not None and prev[1] > 0.0 >= e[0]:
            lo, hi, lines = prev[0], float(g), e[1]
            break
        prev = (float(g), e[0]) if ok else None
    else:
        return None
    for _ in range(8):  # to within 0.2 % in gamma
        mid = 0.5 * (lo + hi)
        e = excess(mid)
        if e is None or e[1] < min_lines:
            break
        lines = e[1]
        if e[0] > 0.0:
            lo = mid
        else:
            hi = mid
    measured = float(np.exp(0.5 * (lo + hi)))
    gamma = 1.0 if abs(measured - 1.0) < LINEAR_SNAP else round(measured, 3)
    return gamma, measured, lines
