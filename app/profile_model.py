"""The band profile model: line box * motion box * Gaussian blur, and its inversion.

A band is ``box(L) * box(w) * gauss(sigma)`` (sweep, line width in camera
pixels, optics).  :mod:`lightflow.app.bands` measures two numbers per band,
both scale-free: the full width ``m`` at half of the band's plateau (the
plateau taken as the mean over the central half of a first half-maximum
width) and the ramp ``r`` from the 50 % to the 20 % level.  For long bands
``m == L`` exactly; when the sweep is not much longer than ``w + 4 sigma`` the
plateau is never reached and ``m`` overshoots.  This module tabulates
``m(L, w)`` and ``r(L, w)`` (unit sigma) from the exact profile (closed form
with the integrated normal CDF) and inverts them:

* :func:`fit_blur` finds the blur that makes every band's ramp consistent;
* :class:`LengthCorrector` recovers ``L`` from ``m`` given ``w`` and ``sigma``.

Everything is in units of sigma, so one table serves every rig.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

_INV_SQRT2 = 1.0 / math.sqrt(2.0)
_INV_SQRT2PI = 1.0 / math.sqrt(2.0 * math.pi)

#: table axes (unit sigma): sweep L and line width w
L_STEP = 0.125
L_AXIS = np.arange(0.0, 96.0 + L_STEP, L_STEP)
W_STEP = 0.125
W_AXIS = np.arange(0.0, 24.0 + W_STEP, W_STEP)
M_STEP = 0.125
M_AXIS = np.arange(0.0, 100.0 + M_STEP, M_STEP)


@nb.njit(cache=True, inline="always")
def _G(t):
    """Antiderivative of the standard normal CDF: t Phi(t) + phi(t)."""
    return t * 0.5 * (1.0 + math.erf(t * _INV_SQRT2)) + math.exp(-0.5 * t * t) * _INV_SQRT2PI


@nb.njit(cache=True)
def profile(x, L, w):
    """Band profile at ``x`` (sigma = 1, unnormalised): box(L) * box(w) * gauss(1)."""
    a = 0.5 * L
    b = 0.5 * max(w, 1e-6)
    return (_G(x + a + b) - _G(x + a - b) - _G(x - a + b) + _G(x - a - b)) / (2.0 * b)


@nb.njit(cache=True)
def _crossing(L, w, level):
    lo = 0.0
    hi = 0.5 * (L + w) + 12.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        if profile(mid, L, w) >= level:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


@nb.njit(cache=True)
def measure(L, w):
    """What the band detector reports for a band with unit blur: ``(m, r)``."""
    top = profile(0.0, L, w)
    x1 = _crossing(L, w, 0.5 * top)
    n = 33
    s = 0.0
    for k in range(n):
        s += profile(x1 * (-0.5 + k / (n - 1.0)), L, w)
    plateau = s / n
    x2 = _crossing(L, w, 0.5 * plateau)
    x20 = _crossing(L, w, 0.2 * plateau)
    return 2.0 * x2, x20 - x2


@nb.njit(cache=True, parallel=True)
def _measure_table(l_axis, w_axis, m_out, r_out):
    for i in nb.prange(w_axis.shape[0]):
        for j in range(l_axis.shape[0]):
            m, r = measure(l_axis[j], w_axis[i])
            m_out[i, j] = m
            r_out[i, j] = r


@nb.njit(cache=True, parallel=True)
def _invert_table(m_tab, l_axis, m_axis, out):
    """Per w row: L at each m of ``m_axis`` on the informative part of m(L)."""
    nw, nl = m_tab.shape
    for i in nb.prange(nw):
        # informative: from the first L where dm/dL > 0.25 on
        first = nl
        for j in range(nl - 1):
            if (m_tab[i, j + 1] - m_tab[i, j]) / (l_axis[j + 1] - l_axis[j]) > 0.25:
                first = j
                break
        for k in range(m_axis.shape[0]):
            out[i, k] = np.nan
            mv = m_axis[k]
            if first >= nl - 1 or mv < m_tab[i, first]:
                continue
            for j in range(first, nl - 1):
                a = m_tab[i, j]
                b = m_tab[i, j + 1]
                if a <= mv <= b and b > a:
                    out[i, k] = l_axis[j] + (mv - a) / (b - a) * (l_axis[j + 1] - l_axis[j])
                    break


@nb.njit(cache=True, parallel=True)
def _bilinear(table, step0, step1, x0, x1, out):
    n0, n1 = table.shape
    flat0 = x0.ravel()
    flat1 = x1.ravel()
    res = out.ravel()
    for k in nb.prange(flat0.shape[0]):
        a = flat0[k] / step0
        b = flat1[k] / step1
        if not (a >= 0.0 and b >= 0.0 and a <= n0 - 1 and b <= n1 - 1):
            res[k] = np.nan
            continue
        i = min(int(a), n0 - 2)
        j = min(int(b), n1 - 2)
        fa = a - i
        fb = b - j
        res[k] = (
            (1 - fa) * (1 - fb) * table[i, j]
            + fa * (1 - fb) * table[i + 1, j]
            + (1 - fa) * fb * table[i, j + 1]
            + fa * fb * table[i + 1, j + 1]
        )


class ProfileTables:
    """Forward tables m(w, L), r(w, L) and the inverse L(w, m), unit sigma."""

    def __init__(self):
        nw, nl = len(W_AXIS), len(L_AXIS)
        self.m = np.empty((nw, nl))
        self.r = np.empty((nw, nl))
        _measure_table(L_AXIS, W_AXIS, self.m, self.r)
        self.inverse = np.empty((nw, len(M_AXIS)))
        _invert_table(self.m, L_AXIS, M_AXIS, self.inverse)

    def true_length(self, m: np.ndarray, w: np.ndarray, sigma) -> np.ndarray:
        """Sweep ``L`` from measured ``m``, line width ``w`` and blur ``sigma`` (camera px).

        NaN where the sweep is hidden in the line width and blur (static lines).
        """
        out = np.empty(np.broadcast(m, w, sigma).shape)
        m_n = np.ascontiguousarray(np.broadcast_to(m / sigma, out.shape), dtype=np.float64)
        w_n = np.ascontiguousarray(np.broadcast_to(w / sigma, out.shape), dtype=np.float64)
        _bilinear(self.inverse, W_STEP, M_STEP, w_n, m_n, out)
        return out * sigma

    def ramp(self, L: np.ndarray, w: np.ndarray, sigma) -> np.ndarray:
        """Predicted 50->20 % ramp of a band (camera px)."""
        out = np.empty(np.broadcast(L, w, sigma).shape)
        l_n = np.ascontiguousarray(np.broadcast_to(L / sigma, out.shape), dtype=np.float64)
        w_n = np.ascontiguousarray(np.broadcast_to(w / sigma, out.shape), dtype=np.float64)
        _bilinear(self.r, W_STEP, L_STEP, w_n, l_n, out)
        return out * sigma


_TABLES: ProfileTables | None = None


def tables() -> ProfileTables:
    """The shared tables (built once per process, about 0.2 s)."""
    global _TABLES
    if _TABLES is None:
        _TABLES = ProfileTables()
    return _TABLES


def fit_blur(m, r, line, scale, max_pixels: int = 3000):
    """Fit the blur model ``sigma^2 = a + b * scale^2`` to measured bands.

    Camera blur and pixel size (``a``) are fixed in camera pixels; projector
    defocus (``b``, in projector px^2) scales with the local magnification
    ``scale`` like the line width.  For each candidate the measured widths are
    corrected to sweeps and the ramps those sweeps imply are compared with the
    measured ramps; the candidate with the smallest median mismatch wins.

    Parameters
    ----------
    m, r, line, scale : numpy.ndarray
        Measured width at half height, ramp, line width (camera px) and
        magnification per pixel.

    Returns
    -------
    (a, b) : tuple of float, or None when there are too few bands.
    """
    ok = np.isfinite(m) & np.isfinite(r) & np.isfinite(line) & np.isfinite(scale)
    idx = np.flatnonzero(ok)
    if idx.size < 50:
        return None
    idx = idx[:: max(1, idx.size // max_pixels)]
    m, r, line, s2 = m.ravel()[idx], r.ravel()[idx], line.ravel()[idx], scale.ravel()[idx] ** 2
    t = tables()
    best, best_cost = None, np.inf
    spread = np.ptp(s2) > 0.15 * np.mean(s2)
    a_grid = np.geomspace(0.02, 6.0, 24)
    b_grid = np.concatenate([[0.0], np.geomspace(0.02, 4.0, 12)]) if spread else [0.0]
    for b in b_grid:
        for a in a_grid:
            sigma = np.sqrt(a + b * s2)
            L = t.true_length(m, line, sigma)
            pred = t.ramp(L, line, sigma)
            res = np.abs(pred - r)
            fin = np.isfinite(res)
            if fin.sum() < 0.3 * res.size:
                continue
            cost = np.median(res[fin]) + 0.5 * (1 - fin.mean())
            if cost < best_cost:
                best, best_cost = (float(a), float(b)), cost
    return best
