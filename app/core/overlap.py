"""Sweeps of bands longer than the line interval, from the periodic row signal (numba).

When a line's sweep ``L`` exceeds its interval ``B`` minus line width and blur,
neighbouring bands merge and :mod:`lightflow.app.core.bands` rejects them.  The
merged signal is still informative.  With identical bands spaced ``B`` (the
model of :mod:`lightflow.app.core.profile_model`: ``I * box(L) * box(w) / L``,
blurred by ``gauss(sigma)``, pixel-integrated) and ``L = (n + f) B`` with
``n`` an integer and ``0 < f < 1``, every point is covered by ``n`` or ``n + 1``
swept lines, so the row is a constant plus a train of *pulses*: bands of sweep
``f B`` and height ``h = I w / L`` (the band's plateau height), centred on the
lines' trajectory centres when ``n`` is even and half-way between them when
``n`` is odd.  Its Fourier coefficients at harmonics ``m / B`` are::

    C_0 = bg + h (n + f)          (= bg + I w / B)
    C_m = h K_m sin(pi m f) / (pi m) exp(-2 pi i m x0 / B),
    K_m = sinc(m w / B) sinc(m / B) exp(-2 pi^2 sigma^2 m^2 / B^2)

(``x0`` a pulse centre, ``sinc(m / B)`` the pixel's own width).  This module
fits those harmonics by linear least squares over a stretch of a row (no
thresholds), then fits ``(h, f, x0)`` to them by Gauss-Newton.

What the stretch alone gives, and what it does not:

* ``f`` (the fractional part of ``L / B``) comes from the pulse *shape*
  (``C_2 / C_1 = cos(pi f) K_2 / K_1`` and the higher ratios), independent of
  the line intensity and the background.  It is not measurable near
  ``f = 0`` and ``f = 1``: the pulses shrink to the line-and-blur profile or
  fill the period, their shape stops depending on ``f`` (``f`` and ``h``
  become one product), and at integer ``L / B`` the row is flat.  The fit's
  covariance, with the noise taken as the larger of the fit residual and a
  noise floor, decides this: a stretch is measurable when the predicted
  standard deviation of ``L`` is at most ``max_rel_std`` of ``L``.
* The integer part ``n`` is *not* in the shape (the same pulses arise for
  every ``n``).  It needs one of these references, which the caller passes:

  - the background ``bg`` under the bands (from the gaps of nearby
    non-overlapping bands on the same surface, or a calibrated ambient
    level): then ``L / B = (C_0 - bg) / h``.  Its error in interval units is
    ``bg error / h``, so ``bg`` must be known to better than about a third of
    the band height ``h`` -- and ``h`` falls as ``1 / L``: this works for
    ``n`` up to 2-3 on bright surfaces, not beyond.
  - a coarse prior ``L / B`` (continuity with neighbouring measured sweeps,
    a previous frame, or another pattern): it must lie within
    ``0.5 - integer_margin - 2 prior_std`` (0.3) intervals of the truth.
  - the trajectory centre of one line (``centre``): the pulses sit on the
    centres for even ``n`` and between them for odd ``n``, so the parity of
    ``n`` follows and a reference only needs to be within
    ``1 - integer_margin - 2 std`` (0.8 for a prior) intervals.  The
    centres are not known from one row of one pattern; they are an input for
    a caller that has them.

  With no reference, or references that disagree, the stretch is
  :data:`OV_AMBIGUOUS` (NaN).
* The interval ``B`` is an input (:func:`refine_interval` refines a guess by
  the same least squares), as are the line width ``w`` in camera pixels and
  the blur ``sigma`` (both as the pipeline knows them).  The model assumes a
  constant ``L``, ``B``, ``I`` and ``bg`` over the stretch: a stretch of 2-3
  intervals on a smooth surface.  Stretches that do not fit the pulse model
  (an edge, print, a changing interval) are :data:`OV_IRREGULAR`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from .bands import (
    BAND_OVERLAP,
    BAND_PERIODIC,
    BAND_VALID,
    F_CENTRE,
    F_FLOOR,
    F_HEIGHT,
    F_INTERVAL,
    F_LENGTH,
    F_VALID,
    FLOOR_GAPS,
    N_FIELDS,
    nearest_partners,
    row_signals,
)
from .medians import median_in_place
from .threads import run_rows

#: output fields of :func:`measure_stretch` / :func:`measure_stretches`
(O_SWEEP, O_FRACTION, O_TURNS, O_PULSE, O_STEP, O_MEAN, O_STD, O_NOISE, O_SHAPE,
 O_CODE, O_LEVEL) = range(11)  # fmt: skip
N_OUT = 11
#: ``O_CODE`` values: measured, or why not
OV_MEASURED = 1.0
OV_SHORT = -1.0  # the stretch spans fewer than min_periods intervals
OV_FLAT = -2.0  # the sweep's fraction is not measurable (near an integer L / B)
OV_IRREGULAR = -3.0  # the harmonics do not follow the periodic band model
OV_AMBIGUOUS = -4.0  # the integer part of L / B is not resolved by the references given
#: (code, name) for counting rejections by cause
CODES = ((OV_MEASURED, "measured"), (OV_SHORT, "short"), (OV_FLAT, "flat"),
         (OV_IRREGULAR, "irregular"), (OV_AMBIGUOUS, "ambiguous"))  # fmt: skip

#: numba options of every kernel: no C-callable wrapper (only for first-class function
#: use, which no caller makes; each cost a share of the kernels' first-run compilation)
_NO_CFUNC = {"no_cfunc_wrapper": True}
#: helpers only called from other kernels: no Python wrapper either
_INTERNAL = {"no_cfunc_wrapper": True, "no_cpython_wrapper": True}

_P_HARM, _P_MINPER, _P_FLOOR, _P_RELSTD, _P_SHAPE, _P_MARGIN, _P_BGSTD, _P_PRIORSTD = range(8)


@dataclass(frozen=True)
class OverlapParams:
    """Tuning of the periodic-stretch measurement.

    Attributes
    ----------
    max_harmonics : int
        Most harmonics fitted (fewer when ``B`` is short: at most ``B / 2.5``).
    min_periods : float
        Shortest stretch, in line intervals.
    noise_floor : float
        Smallest noise (signal units, e.g. DN) assumed for the covariance, so that
        noise-free rows are judged by the model's conditioning, not by zero residuals.
    max_rel_std : float
        A stretch is measurable when the predicted standard deviation of ``L`` is at
        most this fraction of ``L``.
    max_shape_residual : float
        Largest rms misfit of the harmonics to the pulse model, relative to their rms.
    integer_margin : float
        A reference must place ``L / B - f`` within ``0.5 - integer_margin`` of an
        integer (``1 - integer_margin`` of an integer of the right parity).
    bg_std : float
        Uncertainty of a given background (signal units), added to the reference's
        spread in units of the fitted step height.
    prior_std : float
        Uncertainty of a given prior ``L / B`` (intervals).
    """

    max_harmonics: int = 12
    min_periods: float = 2.0
    noise_floor: float = 0.5
    max_rel_std: float = 0.004
    max_shape_residual: float = 0.05
    integer_margin: float = 0.1
    bg_std: float = 1.0
    prior_std: float = 0.05

    def as_array(self) -> np.ndarray:
        """The parameters in the order the numba kernels read them."""
        return np.array([self.max_harmonics, self.min_periods, self.noise_floor,
                         self.max_rel_std, self.max_shape_residual, self.integer_margin,
                         self.bg_std, self.prior_std], dtype=np.float64)  # fmt: skip


@nb.njit(cache=True, error_model="numpy", inline="always", **_INTERNAL)
def _sinc(x):
    if abs(x) < 1e-12:
        return 1.0
    return math.sin(math.pi * x) / (math.pi * x)


@nb.njit(cache=True, error_model="numpy", **_INTERNAL)
def chirp_position(t, tc, g):
    """Position at which lines ``B (1 + g (t - tc))`` apart are ``B`` apart.

    ``tc + ln(1 + g (t - tc)) / g``: its derivative is ``1 / (1 + g (t - tc))``,
    the local interval's inverse, relative to ``B``.
    """
    if g == 0.0:
        return t
    return tc + math.log1p(g * (t - tc)) / g


@nb.njit(cache=True, error_model="numpy", **_INTERNAL)
def harmonic_fit(x, lo, hi, B, M, coef, var_c, chirp=0.0):
    """Least-squares Fourier series of period ``B`` over samples ``x[lo:hi]``.

    Fits ``a_0 + sum_m a_m cos(2 pi m t / B) + b_m sin(2 pi m t / B)`` with ``t``
    the sample position relative to ``lo``.  Writes ``coef[0] = a_0``,
    ``coef[2m-1], coef[2m] = Re C_m, Im C_m`` with ``C_m = (a_m - i b_m) / 2`` (so
    the series is ``sum_m C_m exp(2 pi i m t / B)``) and ``var_c[m]`` the mean
    variance of ``Re C_m`` and ``Im C_m`` per unit noise variance.

    With ``chirp`` = ``g`` the interval changes along the stretch as
    ``B (1 + g (t - tc))`` (``tc`` its middle): ``t`` is then replaced by
    :func:`chirp_position`, in which the lines are ``B`` apart.

    Returns
    -------
    float
        The residual rms (``sqrt(RSS / (N - P))``), NaN when the system is singular.
    """
    N = hi - lo
    P = 2 * M + 1
    w = 2.0 * math.pi / B
    tc = 0.5 * (N - 1)
    Sc = np.empty(2 * M + 1)
    Ss = np.empty(2 * M + 1)
    Sc[0] = N
    Ss[0] = 0.0
    if chirp == 0.0:
        # closed-form sums Sc(k) + i Ss(k) = sum_t exp(i k w t), k = 0 .. 2M (k w is
        # never a multiple of 2 pi: 2M < B): O(M^2), no design matrix
        for k in range(1, 2 * M + 1):
            th = k * w
            amp = math.sin(0.5 * N * th) / math.sin(0.5 * th)
            Sc[k] = amp * math.cos(0.5 * (N - 1) * th)
            Ss[k] = amp * math.sin(0.5 * (N - 1) * th)
    else:
        # the same sums over the warped positions (products of harmonics are
        # harmonics at the sum and difference frequencies whatever the positions)
        for k in range(1, 2 * M + 1):
            Sc[k] = 0.0
            Ss[k] = 0.0
        for j in range(N):
            th = w * chirp_position(float(j), tc, chirp)
            c1, s1 = math.cos(th), math.sin(th)
            c, s = 1.0, 0.0
            for k in range(1, 2 * M + 1):
                c, s = c * c1 - s * s1, s * c1 + c * s1
                Sc[k] += c
                Ss[k] += s
    G = np.empty((P, P))
    G[0, 0] = N
    for a in range(1, M + 1):
        G[0, 2 * a - 1] = G[2 * a - 1, 0] = Sc[a]
        G[0, 2 * a] = G[2 * a, 0] = Ss[a]
        for b in range(1, M + 1):
            d = abs(a - b)
            sd = Ss[d] if b >= a else -Ss[d]  # sum sin((b - a) w t)
            G[2 * a - 1, 2 * b - 1] = 0.5 * (Sc[d] + Sc[a + b])
            G[2 * a, 2 * b] = 0.5 * (Sc[d] - Sc[a + b])
            G[2 * a - 1, 2 * b] = 0.5 * (Ss[a + b] + sd)  # sum cos(a w t) sin(b w t)
            G[2 * b, 2 * a - 1] = G[2 * a - 1, 2 * b]
    # right-hand side by rotating exp(i w t) harmonic by harmonic
    rhs = np.zeros(P)
    sxx = 0.0
    c1, s1 = math.cos(w), math.sin(w)
    cr, sr = 1.0, 0.0  # exp(i w t)
    for j in range(N):
        v = x[lo + j]
        sxx += v * v
        rhs[0] += v
        if chirp != 0.0:
            th = w * chirp_position(float(j), tc, chirp)
            cr, sr = math.cos(th), math.sin(th)
        cm, sm = cr, sr
        for m in range(1, M + 1):
            rhs[2 * m - 1] += v * cm
            rhs[2 * m] += v * sm
            cm, sm = cm * cr - sm * sr, sm * cr + cm * sr
        cr, sr = cr * c1 - sr * s1, sr * c1 + cr * s1
        if j % 64 == 63:  # keep the rotation on the unit circle
            cr, sr = math.cos(w * (j + 1)), math.sin(w * (j + 1))
    # solve G sol = rhs by Cholesky (G overwritten by its factor), and diag(G^-1): the
    # systems are 9-25 unknowns (LAPACK's call overhead would dominate); in line, not
    # a kernel of its own (each costs a share of a first run's compilation)
    for j in range(P):
        d = G[j, j]
        for k in range(j):
            d -= G[j, k] * G[j, k]
        if not (d > 1e-12 * G[0, 0]):
            return np.nan  # not positive definite
        d = math.sqrt(d)
        G[j, j] = d
        for i in range(j + 1, P):
            v = G[i, j]
            for k in range(j):
                v -= G[i, k] * G[j, k]
            G[i, j] = v / d
    # forward and back substitution
    y = np.empty(P)
    for i in range(P):
        v = rhs[i]
        for k in range(i):
            v -= G[i, k] * y[k]
        y[i] = v / G[i, i]
    sol = np.empty(P)
    for i in range(P - 1, -1, -1):
        v = y[i]
        for k in range(i + 1, P):
            v -= G[k, i] * sol[k]
        sol[i] = v / G[i, i]
    # diag(G^-1) = column sums of squares of L^-1
    Li = np.zeros((P, P))
    for j in range(P):
        Li[j, j] = 1.0 / G[j, j]
        for i in range(j + 1, P):
            v = 0.0
            for k in range(j, i):
                v -= G[i, k] * Li[k, j]
            Li[i, j] = v / G[i, i]
    dinv = np.empty(P)
    for j in range(P):
        v = 0.0
        for i in range(j, P):
            v += Li[i, j] * Li[i, j]
        dinv[j] = v
    dot = 0.0  # a loop: numba's np.dot compiles a BLAS wrapper (a second of a first run)
    for i in range(P):
        dot += sol[i] * rhs[i]
    rss = max(sxx - dot, 0.0)
    coef[0] = sol[0]
    var_c[0] = dinv[0]
    for m in range(1, M + 1):
        coef[2 * m - 1] = 0.5 * sol[2 * m - 1]
        coef[2 * m] = -0.5 * sol[2 * m]
        var_c[m] = 0.125 * (dinv[2 * m - 1] + dinv[2 * m])
    return math.sqrt(rss / max(N - P, 1))


@nb.njit(cache=True, error_model="numpy", **_INTERNAL)
def transfer(m, B, w, sigma):
    """``K_m``: the line box, the pixel box and the blur at harmonic ``m / B``."""
    return _sinc(m * w / B) * _sinc(m / B) * math.exp(-2.0 * (math.pi * sigma * m / B) ** 2)


@nb.njit(cache=True, error_model="numpy", **_INTERNAL)
def _pulse_fit(coef, M, B, K, hfx):
    """Gauss-Newton fit of ``(h, f, x0)`` to the harmonics; returns (JtJ^-1 diag, misfit).

    ``hfx`` holds the start and receives the result; the returned array is
    ``[var_h, var_f, var_x0, rms misfit]`` per unit variance of a coefficient part.
    """
    h, f, x0 = hfx[0], hfx[1], hfx[2]
    out = np.empty(4)
    for a in range(4):
        out[a] = np.nan
    # scratch allocated once, cleared by loops (slice assignments compile kernels of their own)
    JtJ = np.empty((3, 3))
    Jtr = np.empty(3)
    inv = np.empty((3, 3))
    step = np.empty(3)
    for _it in range(30):
        for a in range(3):
            Jtr[a] = 0.0
            for b in range(3):
                JtJ[a, b] = 0.0
        # exp(i th_m) and exp(i pi m f) by rotation, harmonic by harmonic
        th1 = -2.0 * math.pi * x0 / B
        c1, s1 = math.cos(th1), math.sin(th1)
        p1c, p1s = math.cos(math.pi * f), math.sin(math.pi * f)
        c, s = 1.0, 0.0
        pc, ps = 1.0, 0.0
        for m in range(1, M + 1):
            c, s = c * c1 - s * s1, s * c1 + c * s1
            pc, ps = pc * p1c - ps * p1s, ps * p1c + pc * p1s
            S = ps / (math.pi * m)
            dS = pc
            km = K[m]
            # model: h K S (c + i s); residual parts
            rr = coef[2 * m - 1] - h * km * S * c
            ri = coef[2 * m] - h * km * S * s
            # d/dh, d/df, d/dx0 of (Re, Im); d th / d x0 = -2 pi m / B
            g = -2.0 * math.pi * m / B
            jr = (km * S * c, h * km * dS * c, -h * km * S * s * g)
            ji = (km * S * s, h * km * dS * s, h * km * S * c * g)
            for a in range(3):
                Jtr[a] += jr[a] * rr + ji[a] * ri
                for b in range(3):
                    JtJ[a, b] += jr[a] * jr[b] + ji[a] * ji[b]
        # inverse of the symmetric JtJ by cofactors (singular: no fit)
        a_ = JtJ
        inv[0, 0] = a_[1, 1] * a_[2, 2] - a_[1, 2] * a_[2, 1]
        inv[0, 1] = a_[0, 2] * a_[2, 1] - a_[0, 1] * a_[2, 2]
        inv[0, 2] = a_[0, 1] * a_[1, 2] - a_[0, 2] * a_[1, 1]
        inv[1, 1] = a_[0, 0] * a_[2, 2] - a_[0, 2] * a_[2, 0]
        inv[1, 2] = a_[0, 2] * a_[1, 0] - a_[0, 0] * a_[1, 2]
        inv[2, 2] = a_[0, 0] * a_[1, 1] - a_[0, 1] * a_[1, 0]
        inv[1, 0], inv[2, 0], inv[2, 1] = inv[0, 1], inv[0, 2], inv[1, 2]
        det = a_[0, 0] * inv[0, 0] + a_[0, 1] * inv[1, 0] + a_[0, 2] * inv[2, 0]
        if not (abs(det) > 1e-300):
            return out
        for a in range(3):
            for b in range(3):
                inv[a, b] = inv[a, b] / det
        for a in range(3):  # inv @ Jtr, as a loop (see harmonic_fit)
            step[a] = 0.0
            for b in range(3):
                step[a] += inv[a, b] * Jtr[b]
        h += step[0]
        f += step[1]
        x0 += step[2]
        # stay inside (0, 1): the pulse train of f and of 1 - f (inverted) differ in sign of h
        f = min(max(f, 1e-4), 1.0 - 1e-4)
        if abs(step[1]) < 1e-10 and abs(step[2]) < 1e-8 * B:
            break
    res = 0.0
    tot = 0.0
    for m in range(1, M + 1):
        th = -2.0 * math.pi * m * x0 / B
        S = math.sin(math.pi * m * f) / (math.pi * m)
        rr = coef[2 * m - 1] - h * K[m] * S * math.cos(th)
        ri = coef[2 * m] - h * K[m] * S * math.sin(th)
        res += rr * rr + ri * ri
        tot += coef[2 * m - 1] ** 2 + coef[2 * m] ** 2
    # inv is already JtJ's inverse: the last iteration computed both
    hfx[0], hfx[1], hfx[2] = h, f, x0
    out[0], out[1], out[2] = inv[0, 0], inv[1, 1], inv[2, 2]
    out[3] = math.sqrt(res / max(tot, 1e-300))
    return out


@nb.njit(cache=True, error_model="numpy", **_INTERNAL)
def measure_stretch(x, lo, hi, B, chirp, w, sigma, bg, bg_err, prior, centre, params, out):
    """Sweep ``L`` of the bands in ``x[lo:hi]``, a stretch of one row with lines ``B`` apart.

    Parameters
    ----------
    x : numpy.ndarray
        One row's signal (float, linear in light).
    lo, hi : int
        The stretch (at least ``min_periods * B`` samples).
    B, w, sigma : float
        Line interval, line width and blur sigma along the row (camera px), at the
        stretch's middle.
    chirp : float
        Relative change of the interval per pixel along the stretch (``dB/dx / B``;
        0 for a constant interval): the lines are fitted at their warped positions
        (:func:`chirp_position`).  The sweep is taken as the same share of the
        interval all along.
    bg : float
        Background under the bands (signal units), NaN if unknown.
    bg_err : float
        Uncertainty of ``bg`` known for this stretch (signal units), added to
        ``bg_std`` (NaN or 0: none).
    prior : float
        A coarse ``L / B`` (intervals), NaN if none.
    centre : float
        The trajectory centre of one line (row position, px), NaN if unknown.
    params : numpy.ndarray
        :meth:`OverlapParams.as_array`.
    out : numpy.ndarray
        ``(N_OUT,)``: ``O_SWEEP`` (L, camera px, NaN unless measured), ``O_FRACTION``
        (``f``), ``O_TURNS`` (``n``), ``O_PULSE`` (a pulse centre, row position),
        ``O_STEP`` (``h``), ``O_MEAN`` (``C_0``), ``O_STD`` (predicted std of ``L``),
        ``O_NOISE`` (residual rms), ``O_SHAPE`` (relative misfit), ``O_CODE``,
        ``O_LEVEL`` (``(C_0 - bg) / h``, the background's reading of ``L / B``).
    """
    for k in range(N_OUT):
        out[k] = np.nan
    out[O_CODE] = OV_SHORT
    N = hi - lo
    if not (B > 2.0) or N < params[_P_MINPER] * B:
        return
    M = int(min(params[_P_HARM], B / 2.5))
    coef = np.zeros(2 * M + 1)
    var_c = np.zeros(M + 1)
    noise = harmonic_fit(x, lo, hi, B, M, coef, var_c, chirp)
    out[O_NOISE] = noise
    out[O_CODE] = OV_FLAT
    if not np.isfinite(noise):
        return
    out[O_MEAN] = coef[0]
    K = np.empty(M + 1)
    for m in range(M + 1):
        K[m] = transfer(m, B, w, sigma)
    # start: x0 from the fundamental's phase (its coefficient is positive at a pulse
    # centre), f from the second harmonic (C_2 / C_1 = cos(pi f) K_2 / K_1)
    c1r, c1i = coef[1], coef[2]
    a1 = math.hypot(c1r, c1i)
    if not (a1 > 0.0):
        return
    x0 = -math.atan2(c1i, c1r) * B / (2.0 * math.pi)
    f0 = 0.5
    if M >= 2:
        th2 = -2.0 * math.pi * 2.0 * x0 / B
        d2 = (coef[3] * math.cos(th2) + coef[4] * math.sin(th2)) / K[2]
        ratio = d2 / (a1 / K[1])
        f0 = math.acos(min(max(ratio, -0.98), 0.98)) / math.pi
    h0 = a1 / K[1] * math.pi / math.sin(math.pi * f0)
    hfx = np.array([h0, f0, x0])
    cov = _pulse_fit(coef, M, B, K, hfx)
    if not np.isfinite(cov[3]):
        return
    h, f, x0 = hfx[0], hfx[1], hfx[2]
    if h < 0.0:
        return
    # noise of one coefficient part (mean over harmonics: nearly equal for stretches of
    # several intervals)
    vc = 0.0
    for m in range(1, M + 1):
        vc += var_c[m]
    s_eff = max(noise, params[_P_FLOOR])
    s_c = s_eff * math.sqrt(vc / M)
    std_f = s_c * math.sqrt(cov[1])
    std_h = s_c * math.sqrt(cov[0])
    out[O_FRACTION] = f
    out[O_STEP] = h
    if np.isfinite(bg):
        out[O_LEVEL] = (coef[0] - bg) / h
    # misfit of the harmonics to the pulse model, relative to their rms (cov[3]); in
    # absolute terms per coefficient part it may reach the noise (2 s_c) plus a share
    # of the signal's own harmonics (a model error the noise does not explain)
    out[O_SHAPE] = cov[3]
    tot = 0.0
    for m in range(1, M + 1):
        tot += coef[2 * m - 1] ** 2 + coef[2 * m] ** 2
    rms_c = math.sqrt(tot / (2 * M))
    misfit = cov[3] * rms_c
    # a pulse centre in row coordinates, nearest to the stretch's middle
    tc = 0.5 * (N - 1)
    x0 += B * round((tc - x0) / B)
    if chirp != 0.0:
        x0 = tc + math.expm1(chirp * (x0 - tc)) / chirp  # back to row positions
    xc = lo + x0
    out[O_PULSE] = xc
    out[O_STD] = B * std_f
    if f <= 2e-4 or f >= 1.0 - 2e-4 or not np.isfinite(std_f):
        out[O_CODE] = OV_FLAT  # the fit ran to f = 0 or 1: no modulation to speak of
        return
    if misfit > math.hypot(2.0 * s_c, params[_P_SHAPE] * rms_c):
        out[O_CODE] = OV_IRREGULAR
        return
    # --- the integer part: from the references given -------------------------------
    parity = -1
    if np.isfinite(centre):
        d = (xc - centre) / B
        d -= round(d)
        parity = 0 if abs(d) < 0.25 else 1
    refs = 0
    lo_n = -1.0e9
    hi_n = 1.0e9
    margin = params[_P_MARGIN]
    reach = 1.0 - margin if parity >= 0 else 0.5 - margin
    if np.isfinite(bg):
        u_dc = out[O_LEVEL]
        # spread of u_dc: background error and the step's own error, in intervals
        bg_sd = params[_P_BGSTD]
        if bg_err > 0.0:
            bg_sd = math.hypot(bg_sd, bg_err)
        sd = math.hypot(bg_sd / h, u_dc * std_h / h)
        span = max(reach - 2.0 * sd, 0.0)
        lo_n = max(lo_n, u_dc - f - span)
        hi_n = min(hi_n, u_dc - f + span)
        refs += 1
    if np.isfinite(prior):
        span = max(reach - 2.0 * params[_P_PRIORSTD], 0.0)
        lo_n = max(lo_n, prior - f - span)
        hi_n = min(hi_n, prior - f + span)
        refs += 1
    n = -1
    count = 0
    if refs > 0:
        for k in range(max(0, int(math.ceil(lo_n))), int(math.floor(hi_n)) + 1):
            if parity < 0 or k % 2 == parity:
                n = k
                count += 1
    if count == 1:
        out[O_TURNS] = n
    if count != 1:
        # judged at one interval more than the fraction (overlap means n >= 1): flat if
        # not even that would be measurable, else only the integer part is missing
        if not (B * std_f <= params[_P_RELSTD] * (f + 1.0) * B):
            out[O_CODE] = OV_FLAT
        else:
            out[O_CODE] = OV_AMBIGUOUS
        return
    L = (n + f) * B
    if not (B * std_f <= params[_P_RELSTD] * L):
        out[O_CODE] = OV_FLAT
        return
    out[O_SWEEP] = L
    out[O_CODE] = OV_MEASURED


@nb.njit(cache=True, error_model="numpy", nogil=True, **_NO_CFUNC)
def _measure_all(rows, row, lo, hi, B, chirp, w, sigma, bg, bg_err, prior, centre, params, out,
                 k0, k1):  # fmt: skip
    for k in range(k0, k1):
        measure_stretch(rows[row[k]], lo[k], hi[k], B[k], chirp[k], w[k], sigma[k], bg[k],
                        bg_err[k], prior[k], centre[k], params, out[k])  # fmt: skip


def measure_stretches(
    rows, row, lo, hi, B, w, sigma, bg=None, prior=None, centre=None, chirp=None,
    params: OverlapParams = OverlapParams(), bg_err=None,
) -> np.ndarray:  # fmt: skip
    """:func:`measure_stretch` over many stretches (vectorised inputs, one per stretch).

    Parameters
    ----------
    rows : numpy.ndarray
        ``(R, W)`` float64 row signals.
    row, lo, hi : numpy.ndarray
        Per stretch: its row index in ``rows`` and its sample range.
    B, w, sigma : numpy.ndarray or float
        Per stretch (or shared): interval, line width, blur (camera px).
    bg, prior, centre : numpy.ndarray, float or None
        Integer-part references (None: unknown everywhere).
    chirp : numpy.ndarray, float or None
        Relative change of the interval per pixel (None: constant intervals).
    params : OverlapParams
    bg_err : numpy.ndarray, float or None
        Per stretch, an uncertainty of ``bg`` beyond ``params.bg_std`` (None: none).

    Returns
    -------
    numpy.ndarray
        ``(S, N_OUT)`` results (fields ``O_*``).
    """
    rows = np.ascontiguousarray(rows, dtype=np.float64)
    row = np.asarray(row, np.int64)
    n = row.shape[0]

    def vec(v, fill=np.nan):
        # always writeable and contiguous (a copy where needed): broadcast views are
        # read-only, and a kernel compiles once per such flag (a live frame would compile)
        v = fill if v is None else v
        return np.require(np.broadcast_to(np.asarray(v, np.float64), (n,)), None, ["C", "W"])

    out = np.empty((n, N_OUT))
    lo = np.asarray(lo, np.int64)
    hi = np.asarray(hi, np.int64)
    # stretches are independent: a band of them per thread (the pipeline's shared pool)
    run_rows(_measure_all, n, rows, row, lo, hi, vec(B), vec(chirp, 0.0), vec(w), vec(sigma),
             vec(bg), vec(bg_err, 0.0), vec(prior), vec(centre), params.as_array(),
             out)  # fmt: skip
    return out


@nb.njit(cache=True, error_model="numpy", **_NO_CFUNC)
def _residual_at(x, lo, hi, B, M):
    coef = np.zeros(2 * M + 1)
    var_c = np.zeros(M + 1)
    return harmonic_fit(x, lo, hi, B, M, coef, var_c)


def refine_interval(x, lo: int, hi: int, B0: float, rel_range: float = 0.1,
                    max_harmonics: int = 12) -> float:  # fmt: skip
    """The period near ``B0`` that best explains ``x[lo:hi]`` as a periodic signal.

    Minimises the residual of :func:`harmonic_fit` over ``B`` in
    ``B0 * (1 +- rel_range)`` by a grid and golden-section search.  A flat row (an
    integer ``L / B``) has no period: the answer is then meaningless, and the
    caller's :func:`measure_stretch` reports it as flat.
    """
    x = np.ascontiguousarray(x, dtype=np.float64)
    M = int(min(max_harmonics, B0 / 2.5))
    grid = B0 * (1.0 + np.linspace(-rel_range, rel_range, 41))
    res = np.array([_residual_at(x, lo, hi, b, M) for b in grid])
    k = int(np.nanargmin(res))
    a, b = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    g = (math.sqrt(5.0) - 1.0) / 2.0
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = _residual_at(x, lo, hi, c, M), _residual_at(x, lo, hi, d, M)
    for _ in range(40):
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = _residual_at(x, lo, hi, c, M)
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = _residual_at(x, lo, hi, d, M)
    return 0.5 * (a + b)


# ---------------------------------------------------------------- runs of rejected bands

#: fewest neighbouring overlap-rejected bands of a row measured as one periodic stretch
#: (the stretch spans one interval more than their centres: three bands, three intervals)
MIN_RUN_BANDS = 3
#: runs of overlap-rejected bands twice this long or longer are measured in pieces of this
#: many bands or more (their sweep changes along the row: a board's 60-97 % of the interval
#: across the image read -8 to +5 % as one stretch, within 2 % in pieces)
RUN_PIECE_BANDS = 5
#: the same for runs without a floor (:func:`_measure_floorless`), in shorter pieces: a
#: stretch's fit takes one sweep and one interval, and where they change along it the pulse
#: shape alone (no floor to hold the level) reads short, the more the longer the stretch
#: (fresh rig 23's slow board: -9.1, -4.7 and -1.4 % in pieces of 8, 5 and 3 bands; chosen
#: on fresh rigs 13-24, the tuning rigs have no such runs)
FLOORLESS_PIECE_BANDS = 3
#: a ``piece`` of :func:`_find_runs` that cuts no run
WHOLE_RUN = 1 << 30
#: a piece keeps its own sweep where it differs from its run's by more than this many of
#: its predicted standard deviations (elsewhere the run's, from more periods, is better)
PIECE_SIGMAS = 2.0
#: how far (line intervals) beyond each end of a run its background is looked for, as the
#: band detector looks for the floor (:data:`~lightflow.app.core.bands.FLOOR_GAPS` gaps)
FLOOR_REACH = FLOOR_GAPS
#: bands past a run's ends continue its pulse train when their spacing, length and height
#: are the run's within this share (a band as long but not a pulse is twice as high or more)
CONTINUATION_TOLERANCE = 0.3
#: sweeps down and up the rows that carry a measured train to the rows above and below,
#: where no clean gap shows the floor (:func:`_flood_trains`; chosen on tuning rigs 4, 9 and
#: 10, whose dense pattern sweeps 1.1-1.8 intervals at the matrix's exposures: their boards
#: read tens of centimetres off where a row's pulses passed for short bands), and how far
#: (line intervals) a band's link to the next row reaches (as the slant's links)
FLOOD_PASSES = 2
FLOOD_REACH = 0.3
#: a train is contradicted where its pulses link (as the flood links them) to bands of a
#: run measured with ``n = 0`` whose ``L / B`` differs from the train's by more than this:
#: one surface's sweep does not jump by half an interval from one row to the next.  Such
#: a run had two references for ``n`` (its floor and its bands' widths), a train measured
#: past its neighbours only its floor, which another surface's gap can supply (fresh rig
#: 19's near board, bands touching at 0.86 intervals: two rows' floors read ``n = 1``,
#: and the flood carried that over the whole board, 226 mm in front of it)
CONTRADICTION_JUMP = 0.5
#: passes of :func:`_measure_floorless` along the rows: each measures the runs of touching
#: bands next to a band measured before (one piece of 3-5 bands further per pass: about as
#: far as four passes of the longer pieces of the other runs reached)
FLOORLESS_PASSES = 7
#: how far (line intervals) from a run's end band the measured band that gives it its
#: ``L / B`` may be, and by how much the measured bands on its two sides may disagree
FLOORLESS_REACH = 1.6
FLOORLESS_AGREE = 0.2
#: their sweeps' largest predicted relative standard deviation, in units of the
#: measurement's (their bands touch: the pulse shape is measured less well than a run's
#: beside a clean gap; the pipeline's 2 % -> 4 %)
FLOORLESS_STD_FACTOR = 2.0
#: largest deviation of a run's centre spacings from their median (share of it): the
#: pulses of overlapping bands are exactly periodic on a smooth surface
RUN_SPACING_TOLERANCE = 0.1
#: a valid band whose gap to its neighbours (interval less its width at half height and
#: the line's width) is narrower than this many blur sigmas reads short alone: the tails
#: of its neighbours fill the gap its background is read from, which the detector's erf
#: model of the tails does not fully take out (rendered rows, tests/test_overlap.py:
#: -0.1 to -0.6 % at 4 sigmas, -0.9 to -1.7 % at 2.7-2.8, -5 % at 0.6).  Runs of such
#: bands are measured on their periodic profile, which has no gap to read (within 0.1 %
#: there).  Not from 4 sigmas: where the alone reading is off by less than the periodic
#: fit's scatter on noisy rows, it is the better one (tuning rigs: a board's p90 11.7 ->
#: 14.7 mm at 4 sigmas, unchanged at 3)
TIGHT_GAP_SIGMAS = 3.0


@nb.njit(cache=True, error_model="numpy", **_NO_CFUNC)
def _find_runs(bands, counts, min_bands, runs, piece):
    """Runs of at least ``min_bands`` neighbouring overlap-rejected bands with centres, runs
    of ``2 piece`` or more cut into pieces of ``piece`` to ``2 piece - 1`` bands (the sweep
    and the interval change along a long run, a stretch's must not; a short piece at a
    run's end would be measured less well: its stretch reaches past the run).

    ``runs[m] = (row, first band, last band)``; returns the number of runs.
    """
    m = 0
    for r in range(counts.shape[0]):
        n = counts[r]
        k = 0
        while k < n:
            if bands[r, k, F_VALID] != BAND_OVERLAP or not np.isfinite(bands[r, k, F_CENTRE]):
                k += 1
                continue
            j = k
            while (j + 1 < n and bands[r, j + 1, F_VALID] == BAND_OVERLAP
                   and np.isfinite(bands[r, j + 1, F_CENTRE])):  # fmt: skip
                j += 1
            if j - k + 1 >= min_bands:
                m = _cut_run(r, k, j, piece, runs, m)
            k = j + 1
    return m


@nb.njit(cache=True, error_model="numpy", **_INTERNAL)
def _cut_run(r, k, j, piece, runs, m):
    """Append run ``k..j`` of row ``r`` to ``runs`` from ``m`` on, cut into pieces of
    ``piece`` to ``2 piece - 1`` bands when it has ``2 piece`` or more (whole otherwise);
    returns the new count (stops when ``runs`` is full)."""
    for first in range(k, j + 2 - piece if j - k + 1 >= piece else k + 1, piece):
        if m == runs.shape[0]:
            break
        runs[m, 0] = r
        runs[m, 1] = first
        runs[m, 2] = first + piece - 1 if j - first + 1 >= 2 * piece else j
        m += 1
    return m


@nb.njit(cache=True, error_model="numpy", **_NO_CFUNC)
def _cut_runs(runs, piece, out):
    """Every run of ``runs`` cut as :func:`_cut_run` does, into ``out``; returns the number of
    pieces, and ``out[:, 3]`` the run each piece belongs to."""
    m = 0
    for q in range(runs.shape[0]):
        start = m
        m = _cut_run(runs[q, 0], runs[q, 1], runs[q, 2], piece, out, m)
        for i in range(start, m):
            out[i, 3] = q
    return m


@nb.njit(cache=True, error_model="numpy", **_NO_CFUNC)
def _find_tight_runs(bands, counts, min_bands, line_per_px, blur_a, blur_b, gap_sigmas, runs):
    """Runs of at least ``min_bands`` neighbouring valid bands whose gaps are narrower than
    ``gap_sigmas`` blur sigmas (:data:`TIGHT_GAP_SIGMAS`), less their outermost bands,
    cut into pieces of ``min_bands`` to ``2 min_bands - 1`` bands.

    A band's line is ``line_per_px * B`` camera px wide and its blur
    ``sqrt(blur_a + blur_b * B^2)`` (``B`` its interval).  ``runs[m] = (row, first band,
    last band)``; returns the number of runs.
    """
    m = 0
    for r in range(counts.shape[0]):
        n = counts[r]
        k = 0
        while k < n:
            j = k
            while j < n and _tight(bands[r, j], line_per_px, blur_a, blur_b, gap_sigmas):
                j += 1
            # without the run's two outermost bands (a stretch reaches half an interval past
            # its end bands: there their neighbours must be), in pieces of min_bands (the
            # last one takes the rest): the interval of a long run changes along it
            # (perspective), a stretch's must not
            for first in range(k + 1, j - 1 - min_bands + 1, min_bands):
                if m == runs.shape[0]:
                    break
                runs[m, 0] = r
                runs[m, 1] = first
                runs[m, 2] = first + min_bands - 1 if j - 1 - first >= 2 * min_bands else j - 2
                m += 1
            k = j + 1
    return m


@nb.njit(cache=True, error_model="numpy", **_INTERNAL)
def _tight(band, line_per_px, blur_a, blur_b, gap_sigmas):
    """Whether a band is valid, with a centre, and its gap narrower than ``gap_sigmas``."""
    b = band[F_INTERVAL]
    if band[F_VALID] != BAND_VALID or not np.isfinite(band[F_CENTRE]) or not b > 0.0:
        return False
    sigma = math.sqrt(max(blur_a + blur_b * b * b, 0.0))
    return b - band[F_LENGTH] - line_per_px * b < gap_sigmas * sigma


@nb.njit(cache=True, error_model="numpy", **_NO_CFUNC)
def _prepare_runs(bands, runs, m, tol, width, out):
    """Per run of one pattern: ``out[q] = (B, lo, hi, floor, width over B, floor spread)``, or
    NaN ``B`` when its centre spacings disagree (more than ``tol`` of their median) with each
    other.  The floor is the lowest of the bands' floors, its spread the highest less the
    lowest: the bands' floors are the lowest gaps a few intervals to either side, so they
    differ where the two sides of the run (or an end of it and a stretch with no clean gap)
    disagree about the background under it."""
    for q in range(m):
        r, k0, k1 = runs[q, 0], runs[q, 1], runs[q, 2]
        n = k1 - k0
        d = np.empty(n)
        for i in range(n):
            d[i] = bands[r, k0 + i + 1, F_CENTRE] - bands[r, k0 + i, F_CENTRE]
        b = median_in_place(d, n)
        out[q, 0] = np.nan
        if not b > 2.0:
            continue
        ok = True
        for i in range(n):
            if abs(d[i] - b) > tol * b:
                ok = False
        if not ok:
            continue
        lengths = np.empty(n + 1)
        floor = np.inf
        top = -np.inf
        for i in range(n + 1):
            lengths[i] = bands[r, k0 + i, F_LENGTH]
            floor = min(floor, bands[r, k0 + i, F_FLOOR])
            top = max(top, bands[r, k0 + i, F_FLOOR])
        out[q, 0] = b
        out[q, 1] = max(0.0, math.floor(bands[r, k0, F_CENTRE] - 0.5 * b))
        out[q, 2] = min(float(width), math.ceil(bands[r, k1, F_CENTRE] + 0.5 * b))
        # NaN floor or width: that reference is missing (then the run stays rejected)
        out[q, 3] = floor if np.isfinite(floor) else np.nan
        out[q, 4] = median_in_place(lengths, n + 1) / b
        out[q, 5] = top - floor if np.isfinite(floor) else np.nan


@nb.njit(cache=True, error_model="numpy", **_NO_CFUNC)
def _lowest_levels(signals, row, lo, hi, reach, out):
    """Lowest mean of five neighbouring samples within ``reach[s]`` before, inside and
    within ``reach[s]`` after each stretch ``lo[s]:hi[s]`` of ``signals[row[s]]``
    (``out[s]``, NaN where the row ends first)."""
    width = signals.shape[1]
    for s in range(row.shape[0]):
        x = signals[row[s]]
        for side in range(3):
            a = (int(lo[s] - reach[s]), int(lo[s]), int(hi[s]))[side]
            b = (int(lo[s]), int(hi[s]), int(hi[s] + reach[s]))[side]
            a = max(a, 0)
            b = min(b, width)
            best = np.nan
            if b - a >= 5:
                run = 0.0
                for i in range(a, a + 5):
                    run += x[i]
                best = run
                for i in range(a + 5, b):
                    run += x[i] - x[i - 5]
                    best = min(best, run)
                best /= 5.0
            out[s, side] = best


def warm_up(params: OverlapParams | None = None) -> None:
    """Compile :func:`measure_runs`'s kernels (numba caches them on disk).

    On three made-up overlapping bands of a flat row: measured as flat, nothing
    marked.  The pipeline's warm-up calls it; the demo's helper process calls it
    too, so that a first run compiles them beside the rest of the pipeline.
    """
    bands = np.full((2, 1, 3, N_FIELDS), np.nan)
    bands[:, 0, :, F_CENTRE] = [20.0, 40.0, 60.0]
    bands[:, 0, :, F_VALID] = BAND_OVERLAP
    bands[:, 0, :, F_FLOOR] = 0.0
    bands[:, 0, :, F_LENGTH] = 15.0
    counts = np.full((2, 1), 3, np.int64)
    measure_runs(np.zeros((1, 80, 3), np.uint8), np.eye(2, 3), np.zeros(1, np.int64), bands,
                 counts, np.ones(2), np.ones(2), np.ones((2, 2)),
                 OverlapParams() if params is None else params)  # fmt: skip
    # the kernels only a measured train reaches (a frame's first train must not wait
    # seconds for them), on the same made-up bands: nothing continues, nothing is carried
    # (the argument types and layouts of measure_runs' calls: B and the sweeps contiguous
    # copies of a table's columns, as one row's column would be anyway)
    runs = np.array([[0, 0, 2]], np.int64)
    one = np.zeros(1, np.int64)
    prep = np.ones((2, 6))
    B = np.ascontiguousarray(prep[:, 0])
    _reject_continuations(bands, counts, one, runs, one, B, prep[:, 4] * B,
                          CONTINUATION_TOLERANCE)  # fmt: skip
    member = np.full(bands.shape[:3], -1, np.int64)
    _flood_trains(bands, counts, one, runs, one, B, prep[:, 4] * B, CONTINUATION_TOLERANCE,
                  FLOOD_REACH, FLOOD_PASSES, member, B, np.zeros(1, np.int64))  # fmt: skip
    _find_member_runs(bands, counts, member, MIN_RUN_BANDS, np.empty((1, 5), np.int64))
    # a long run of touching bands measured again in pieces (none measurable here)
    long = np.full((2, 1, 2 * RUN_PIECE_BANDS, N_FIELDS), np.nan)
    long[:, 0, :, F_CENTRE] = 20.0 * np.arange(1, 2 * RUN_PIECE_BANDS + 1)
    long[:, 0, :, F_VALID] = BAND_PERIODIC
    _measure_pieces(np.zeros((2, 20 * (2 * RUN_PIECE_BANDS + 1))), one, long, one,
                    np.array([[0, 0, 2 * RUN_PIECE_BANDS - 1]], np.int64), np.full(1, 10.0),
                    np.ones(2), np.ones(2), np.ones((2, 2)),
                    OverlapParams() if params is None else params, long.shape[2] * 20)  # fmt: skip


def measure_runs(image, weights, row_y, bands, counts, line_px, pitch, blur,
                 params: OverlapParams, tight_runs: bool = True) -> int:  # fmt: skip
    """Measure the sweeps of runs of overlap-rejected bands, and mark them valid.

    Where neighbouring swept lines overlap, the band detector
    (:mod:`lightflow.app.core.bands`) rejects their bands (``BAND_OVERLAP``).  A run
    of at least :data:`MIN_RUN_BANDS` of them in one row, evenly spaced, is one
    periodic stretch (from half an interval before the first centre to half an
    interval after the last): :func:`measure_stretch` fits its sweep.  The integer
    part ``n`` of ``L / B`` comes from the floor the detector found under the bands
    (``F_FLOOR``, the lowest gap a few intervals to either side).  Touching bands
    (``n = 0``) must also agree with their own widths over the interval (a coarse
    ``L / B``).  Bands swept past their neighbours (``n >= 1``) have no other
    reference (their widths read the pulses, a fraction of the interval): for them the
    floor is as uncertain as the run's bands' floors and the lowest levels on its two
    sides differ (a step of the background, another surface: then no ``n`` is
    resolved).  Measured runs get the sweep as their length, the run's spacing as
    their interval and ``BAND_PERIODIC``.  Where a run is a train of pulses (measured
    with ``n >= 1``), the valid bands that continue it past its ends (same spacing,
    length and height) are more of its pulses, too far from a clean gap for the
    detector's floor test: they become
    ``BAND_OVERLAP`` rather than give a sweep whole intervals short.

    With ``tight_runs``, runs of valid bands whose gaps are narrower than
    :data:`TIGHT_GAP_SIGMAS` blur sigmas, which read short alone, are measured the same
    way (with ``n = 0``); where the periodic profile gives a sweep, it replaces theirs.
    A detector that knew the line width and blur (``edge`` of
    :func:`lightflow.app.core.bands.bands_in_row`) read them right alone.

    Parameters
    ----------
    image : numpy.ndarray
        The ``(H, W, 3)`` image the bands were detected on.
    weights : numpy.ndarray
        ``(2, 3)`` unmixing weights of the patterns.
    row_y : numpy.ndarray
        Image row of each measured row.
    bands, counts : numpy.ndarray
        The detector's output ``(2, R, max_bands, N_FIELDS)`` and ``(2, R)``, updated
        in place.
    line_px, pitch : numpy.ndarray
        Per pattern, the line width and the line pitch (projector px; uniform
        patterns): the line is ``line_px * B / pitch`` camera px wide.
    blur : numpy.ndarray
        ``(2, 2)`` blur model, ``sigma^2 = a + b * (B / pitch)^2`` (camera px).
    params : OverlapParams

    A train measured next to a clean gap (``n >= 1``) is carried to the rows above and
    below it, whose pulses pass for short bands where no clean gap is near
    (:func:`_flood_trains`): those pulses are measured in pieces with the train's
    ``L / B`` as the reference for ``n``, or rejected.

    Returns
    -------
    int
        The number of runs (and pieces of carried pulses) measured.
    """
    width = image.shape[1]
    parts = []
    for p in range(2):
        for tight in (False, True) if tight_runs else (False,):
            # room for every run: each holds MIN_RUN_BANDS bands or more (a row of 60
            # overlapping bands holds one, a row of tight valid bands one per
            # MIN_RUN_BANDS of them)
            size = int(counts[p].sum()) // MIN_RUN_BANDS + 1
            runs = np.empty((size, 3), np.int64)
            if tight:
                m = _find_tight_runs(bands[p], counts[p], MIN_RUN_BANDS, line_px[p] / pitch[p],
                                     blur[p, 0], blur[p, 1] / pitch[p] ** 2, TIGHT_GAP_SIGMAS,
                                     runs)  # fmt: skip
            else:
                m = _find_runs(bands[p], counts[p], MIN_RUN_BANDS, runs, WHOLE_RUN)
            if m == 0:
                continue
            prep = np.empty((m, 6))
            _prepare_runs(bands[p], runs, m, RUN_SPACING_TOLERANCE, width, prep)
            ok = np.isfinite(prep[:, 0]) & np.isfinite(prep[:, 3]) & np.isfinite(prep[:, 4])
            if ok.any():
                parts.append((p, runs[:m][ok], prep[ok], np.full(np.count_nonzero(ok), tight)))
    if not parts:
        # no run has a floor: the measured bands beside them may still give their L / B
        return _measure_floorless(image, weights, row_y, bands, counts, line_px, pitch, blur,
                                  params, {})  # fmt: skip
    # the signals of the rows with runs, both patterns: stretch s reads row 2 i + p
    rows_used = np.unique(np.concatenate([runs[:, 0] for _, runs, _, _ in parts]))
    signals = np.empty((2 * len(rows_used), width))
    for i, r in enumerate(rows_used):
        signals[2 * i : 2 * i + 2] = row_signals(image, int(row_y[r]), weights)
    pat = np.concatenate([np.full(len(runs), p) for p, runs, _, _ in parts])
    runs = np.concatenate([runs for _, runs, _, _ in parts])
    prep = np.concatenate([prep for _, _, prep, _ in parts])
    tight = np.concatenate([tight for _, _, _, tight in parts])
    B, w, sigma = _stretch_optics(prep, pat, line_px, pitch, blur)
    row = 2 * np.searchsorted(rows_used, runs[:, 0]) + pat
    lo, hi = prep[:, 1].astype(np.int64), prep[:, 2].astype(np.int64)
    # the floor's uncertainty when it is the only reference: how much the floors under the
    # run's bands, and the lowest levels on its two sides, differ (a step of the
    # background, another surface)
    # (a side that stays above half-way from the floor to the run's own lowest level shows
    # no floor: its lines overlap too)
    levels = np.empty((len(B), 3))
    _lowest_levels(signals, row, lo, hi, FLOOR_REACH * B, levels)
    half = 0.5 * (levels[:, 1] + prep[:, 3])
    both = (levels[:, 0] < half) & (levels[:, 2] < half)
    bg_err = np.where(both, np.maximum(prep[:, 5], np.abs(levels[:, 0] - levels[:, 2])),
                      prep[:, 5])  # fmt: skip
    # touching bands (n = 0): the floor and the bands' widths over the interval agree (two
    # references: the floor's uncertainty is the parameters')
    out = measure_stretches(signals, row, lo, hi, B, w, sigma, bg=prep[:, 3], prior=prep[:, 4],
                            params=params)  # fmt: skip
    # bands swept past their neighbours: their widths read the pulses (a fraction of the
    # interval) and contradict the floor, which alone gives n (n = 0 is left to the above),
    # as uncertain as it is
    # (bands valid alone are not swept past their neighbours: a tight run measured with
    # n >= 1 keeps its own reading)
    out[tight & (out[:, O_TURNS] != 0), O_CODE] = OV_AMBIGUOUS
    past = np.flatnonzero((out[:, O_CODE] == OV_AMBIGUOUS) & ~tight)
    if len(past):
        alone = measure_stretches(signals, row[past], lo[past], hi[past], B[past], w[past],
                                  sigma[past], bg=prep[past, 3], params=params,
                                  bg_err=bg_err[past])  # fmt: skip
        keep = (alone[:, O_CODE] == OV_MEASURED) & (alone[:, O_TURNS] >= 1)
        out[past[keep]] = alone[keep]
    done = np.flatnonzero((out[:, O_CODE] == OV_MEASURED) & ~tight)
    # touching bands first: they are the references a train must not contradict
    trains = done[out[done, O_TURNS] >= 1]
    touching = done[out[done, O_TURNS] == 0]
    sweep = np.ascontiguousarray(out[:, O_SWEEP])
    _mark_runs(bands, pat, runs, touching, sweep, B, True)
    # a long run of touching bands is one stretch so far, but its sweep changes along the
    # row (perspective): measured again in pieces, with the run's L / B as the reference
    long = touching[runs[touching, 2] - runs[touching, 1] + 1 >= 2 * RUN_PIECE_BANDS]
    if len(long):
        _measure_pieces(signals, row[long], bands, pat[long], runs[long], out[long, O_SWEEP],
                        line_px, pitch, blur, params, width)  # fmt: skip
    # the rows above and below a measured train carry it too, where no clean gap near them
    # gave the floor: their pulses are measured with the train's L / B as the reference
    # for n (those that cannot be stay rejected); a train whose links reach touching bands
    # measured an interval apart from it is not measured, nor carried
    flooded = 0
    if len(trains):
        member = np.full(bands.shape[:3], -1, np.int64)
        contradicted = np.zeros(len(runs), np.int64)
        _flood_trains(bands, counts, pat, runs, trains, B, prep[:, 4] * B,
                      CONTINUATION_TOLERANCE, FLOOD_REACH, FLOOD_PASSES, member, sweep / B,
                      contradicted)  # fmt: skip
        if np.any(contradicted[trains] > 0):
            member[np.isin(member, trains[contradicted[trains] > 0])] = -1
            trains = trains[contradicted[trains] == 0]
        _mark_runs(bands, pat, runs, trains, sweep, B, True)
        # past the ends of a run swept past its neighbours, bands that continue its pulse
        # train are more of its pulses that the detector took for bands (no clean gap showed
        # the floor near them): rejected, not measured whole intervals short
        # (only runs measured so: a run of touching bands has the same spacing, lengths and
        # heights, and the floor's reading alone, O_LEVEL, is off by more than an interval
        # often enough to take one for a train)
        _reject_continuations(bands, counts, pat, runs, trains, B, prep[:, 4] * B,
                              CONTINUATION_TOLERANCE)  # fmt: skip
        carried = (member >= 0) & (bands[..., F_VALID] == BAND_VALID)
        bands[..., F_VALID][carried] = BAND_OVERLAP
        flooded = _measure_flooded(image, weights, row_y, bands, counts, member,
                                   out[:, O_SWEEP] / B, line_px, pitch, blur, params)  # fmt: skip
    # runs of touching bands with no clean gap within reach have no floor: the measured
    # bands beside them in their row give their L / B, a run further per pass
    floorless = _measure_floorless(image, weights, row_y, bands, counts, line_px, pitch, blur,
                                   params, {int(r): signals[2 * i : 2 * i + 2]
                                            for i, r in enumerate(rows_used)})  # fmt: skip
    # tight runs last: the pulses of a train far from any clean gap look like tight valid
    # bands (and their floor like n = 0); those continuing a measured train are rejected
    # by now, and a tight run that holds one is not measured
    measured = np.flatnonzero((out[:, O_CODE] == OV_MEASURED) & tight)
    # every band of each (a tight run holds at most 2 MIN_RUN_BANDS - 1), in one gather: a
    # Python loop over a frame's thousand runs took 1.3 ms
    first, last = runs[measured, 1:2], runs[measured, 2:3]
    k = first + np.arange(2 * MIN_RUN_BANDS - 1)
    codes = bands[pat[measured, None], runs[measured, 0:1], np.minimum(k, last), F_VALID]
    still = np.all((k > last) | (codes == BAND_VALID), axis=1)
    _mark_runs(bands, pat, runs, measured[still], np.ascontiguousarray(out[:, O_SWEEP]), B, True)
    return len(done) + int(np.count_nonzero(still)) + flooded + floorless


def _stretch_optics(prep, pat, line_px, pitch, blur):
    """Per prepared run (:func:`_prepare_runs`) of pattern ``pat``: its interval ``B`` (a
    contiguous copy, one kernel layout), the line's width and the blur there (camera px)."""
    B = np.ascontiguousarray(prep[:, 0])
    mag = B / pitch[pat]
    sigma = np.sqrt(np.maximum(blur[pat, 0] + blur[pat, 1] * mag * mag, 0.01))
    return B, line_px[pat] * mag, sigma


def _measure_pieces(signals, row, bands, pat, runs, sweep, line_px, pitch, blur,
                    params: OverlapParams, width: int) -> None:
    """Measure each run of ``runs`` (its sweep ``sweep``) again in pieces of
    :data:`RUN_PIECE_BANDS` to twice that many bands, with the run's ``L / B`` as the
    reference for ``n``.  A piece takes its own sweep and spacing where it differs from
    the run's by more than :data:`PIECE_SIGMAS` of its predicted error (the sweep changes
    along the run); elsewhere the run's reading stays (it pools more periods: a piece's
    stretch also reaches past the run's ends).  A piece that cannot be measured keeps it
    too, unless another piece of its run took its own (then it is rejected)."""
    cut = np.empty((int((runs[:, 2] - runs[:, 1] + 1).sum()) // RUN_PIECE_BANDS + len(runs), 4),
                   np.int64)  # fmt: skip
    m = _cut_runs(np.ascontiguousarray(runs), RUN_PIECE_BANDS, cut)
    pieces, owner = np.ascontiguousarray(cut[:m, :3]), cut[:m, 3]
    prep = np.empty((m, 6))
    for p in range(2):
        sel = np.flatnonzero(pat[owner] == p)
        if len(sel):
            part = np.empty((len(sel), 6))
            _prepare_runs(bands[p], np.ascontiguousarray(pieces[sel]), len(sel),
                          RUN_SPACING_TOLERANCE, width, part)  # fmt: skip
            prep[sel] = part
    ok = np.flatnonzero(np.isfinite(prep[:, 0]))
    if len(ok) == 0:
        return
    pp = pat[owner[ok]]
    prep = prep[ok]
    B, w, sigma = _stretch_optics(prep, pp, line_px, pitch, blur)
    run_sweep = sweep[owner[ok]]
    out = measure_stretches(signals, row[owner[ok]], prep[:, 1].astype(np.int64),
                            prep[:, 2].astype(np.int64), B, w, sigma,
                            prior=run_sweep / B, params=params)  # fmt: skip
    done = ((out[:, O_CODE] == OV_MEASURED) & (out[:, O_TURNS] == 0)
            & (np.abs(out[:, O_SWEEP] - run_sweep) > PIECE_SIGMAS * out[:, O_STD]))  # fmt: skip
    _mark_runs(bands, pp, np.ascontiguousarray(pieces[ok]), np.flatnonzero(done),
               np.ascontiguousarray(out[:, O_SWEEP]), B, True)  # fmt: skip
    # where a run's sweep changes along it (a piece took its own), its pieces that cannot be
    # measured (near an integer L / B) are rejected: the run's average is off at its ends
    varies = np.zeros(len(runs), bool)
    varies[owner[ok[done]]] = True
    failed = np.ones(m, bool)
    failed[ok[out[:, O_CODE] == OV_MEASURED]] = False
    for i in np.flatnonzero(failed & varies[owner]):
        r, first, last = pieces[i]
        bands[pat[owner[i]], r, first : last + 1, F_VALID] = BAND_OVERLAP


def _measure_floorless(image, weights, row_y, bands, counts, line_px, pitch, blur,
                       params: OverlapParams, signals: dict) -> int:  # fmt: skip
    """Measure the runs of overlap-rejected bands that are still rejected, with the ``L / B``
    of the measured bands beside them in their row as the reference for ``n``, at twice the
    caller's largest relative error (:data:`FLOORLESS_STD_FACTOR`); returns the number
    measured.  Still rejected are the runs without a floor and those whose reading with
    it was flat or ambiguous at the caller's precision (held out, the second kind gave
    gen2028's boards 4-5 points of coverage at the same error).

    Where a surface's bands touch over a wide stretch (a board whose sweep approaches the
    interval), no clean gap within reach shows the floor, so :func:`measure_runs` could not
    tell ``n`` for them.  The sweep changes smoothly along a row, so the nearest measured
    band (valid, or periodic: measured in an earlier pass) within :data:`FLOORLESS_REACH`
    of the run's spacing from its end bands, on either side, gives its ``L / B``; where
    both sides have one they must agree within :data:`FLOORLESS_AGREE`, else the run stays
    rejected (an edge between two surfaces).  :func:`measure_stretch` then keeps ``n`` only
    where the reference lies within 0.3 intervals of a candidate, and only bands that touch
    (``n = 0`` and a gap narrower than :data:`TIGHT_GAP_SIGMAS` blur sigmas) are kept.

    ``signals`` holds the row signals (``(2, W)`` per measured row) already read; the
    rows it lacks are read and added.
    """
    measured = 0
    width = image.shape[1]
    params = dataclasses.replace(params, max_rel_std=FLOORLESS_STD_FACTOR * params.max_rel_std)
    for _ in range(FLOORLESS_PASSES):
        parts = []
        for p in range(2):
            runs = np.empty((int(counts[p].sum()) // MIN_RUN_BANDS + 1, 3), np.int64)
            m = _find_runs(bands[p], counts[p], MIN_RUN_BANDS, runs, FLOORLESS_PIECE_BANDS)
            if m == 0:
                continue
            prep = np.empty((m, 6))
            _prepare_runs(bands[p], runs, m, RUN_SPACING_TOLERANCE, width, prep)
            prior = np.empty(m)
            _row_priors(bands[p], counts[p], runs, m, np.ascontiguousarray(prep[:, 0]),
                        FLOORLESS_REACH, FLOORLESS_AGREE, prior)  # fmt: skip
            ok = np.isfinite(prep[:, 0]) & np.isfinite(prior)
            if ok.any():
                parts.append((p, runs[:m][ok], prep[ok], prior[ok]))
        if not parts:
            break
        pat = np.concatenate([np.full(len(runs), p) for p, runs, _, _ in parts])
        runs = np.concatenate([runs for _, runs, _, _ in parts])
        prep = np.concatenate([prep for _, _, prep, _ in parts])
        prior = np.concatenate([prior for _, _, _, prior in parts])
        for r in np.unique(runs[:, 0]):
            if int(r) not in signals:
                signals[int(r)] = row_signals(image, int(row_y[r]), weights)
        rows_used = np.array(sorted(signals))
        stack = np.stack([signals[int(r)] for r in rows_used]).reshape(2 * len(rows_used), -1)
        B, w, sigma = _stretch_optics(prep, pat, line_px, pitch, blur)
        row = 2 * np.searchsorted(rows_used, runs[:, 0]) + pat
        out = measure_stretches(stack, row, prep[:, 1].astype(np.int64),
                                prep[:, 2].astype(np.int64), B, w, sigma, prior=prior,
                                params=params)  # fmt: skip
        # bands that touch (n = 0, no gap wider than TIGHT_GAP_SIGMAS blur sigmas) only: a
        # train's pulses pass for valid bands where no floor is near (a whole number of
        # intervals short), and their L / B would make a train read as short touching bands
        gap = B - out[:, O_SWEEP] - w
        done = np.flatnonzero((out[:, O_CODE] == OV_MEASURED) & (out[:, O_TURNS] == 0)
                              & (gap < TIGHT_GAP_SIGMAS * sigma))  # fmt: skip
        if len(done) == 0:
            break
        _mark_runs(bands, pat, runs, done, np.ascontiguousarray(out[:, O_SWEEP]), B, True)
        measured += len(done)
    return measured


@nb.njit(cache=True, error_model="numpy", **_NO_CFUNC)
def _row_priors(bands, counts, runs, m, spacing, reach, agree, out):
    """Per run of one pattern, the ``L / B`` of the nearest measured band (valid or
    periodic, with an interval) in its row within ``reach`` of the run's ``spacing`` from
    its end bands, the mean of the two sides' where both have one and they agree within
    ``agree``; NaN where neither side has one or they disagree."""
    for q in range(m):
        r, k0, k1 = runs[q, 0], runs[q, 1], runs[q, 2]
        limit = reach * spacing[q]  # not an end band's own interval: it can be NaN
        n = counts[r]
        sides = np.full(2, np.nan)
        for side in range(2):
            k = k0 - 1 if side == 0 else k1 + 1
            end = bands[r, k0 if side == 0 else k1]
            step = -1 if side == 0 else 1
            while 0 <= k < n:
                b = bands[r, k]
                if not abs(b[F_CENTRE] - end[F_CENTRE]) <= limit:
                    break
                if (b[F_VALID] == BAND_VALID or b[F_VALID] == BAND_PERIODIC) and b[F_INTERVAL] > 0:
                    sides[side] = b[F_LENGTH] / b[F_INTERVAL]
                    break
                k += step
        if np.isfinite(sides[0]) and np.isfinite(sides[1]):
            out[q] = 0.5 * (sides[0] + sides[1]) if abs(sides[0] - sides[1]) <= agree else np.nan
        elif np.isfinite(sides[0]):
            out[q] = sides[0]
        else:
            out[q] = sides[1]


def _measure_flooded(image, weights, row_y, bands, counts, member, train_sweeps, line_px,
                     pitch, blur, params: OverlapParams) -> int:  # fmt: skip
    """Measure the runs of pulses :func:`_flood_trains` found, each with its train's ``L / B``
    as the reference for ``n`` (``train_sweeps``, per run of ``member``); returns the number
    measured.  Their own rows show no clean gap: the floor is no reference there."""
    size = int(counts.sum()) // MIN_RUN_BANDS + 1
    found = np.empty((size, 5), np.int64)
    m = _find_member_runs(bands, counts, member, MIN_RUN_BANDS, found)
    if m == 0:
        return 0
    found = found[:m]
    prep = np.empty((m, 6))
    pat = found[:, 0]
    for p in range(2):
        sel = np.flatnonzero(pat == p)
        if len(sel):
            part = np.empty((len(sel), 6))
            _prepare_runs(bands[p], np.ascontiguousarray(found[sel, 1:4]), len(sel),
                          RUN_SPACING_TOLERANCE, image.shape[1], part)  # fmt: skip
            prep[sel] = part
    ok = np.isfinite(prep[:, 0])
    if not ok.any():
        return 0
    found, prep, pat = found[ok], prep[ok], pat[ok]
    rows_used = np.unique(found[:, 1])
    signals = np.empty((2 * len(rows_used), image.shape[1]))
    for i, r in enumerate(rows_used):
        signals[2 * i : 2 * i + 2] = row_signals(image, int(row_y[r]), weights)
    B, w, sigma = _stretch_optics(prep, pat, line_px, pitch, blur)
    row = 2 * np.searchsorted(rows_used, found[:, 1]) + pat
    out = measure_stretches(signals, row, prep[:, 1].astype(np.int64),
                            prep[:, 2].astype(np.int64), B, w, sigma,
                            prior=train_sweeps[found[:, 4]], params=params)  # fmt: skip
    done = np.flatnonzero((out[:, O_CODE] == OV_MEASURED) & (out[:, O_TURNS] >= 1))
    _mark_runs(bands, pat, np.ascontiguousarray(found[:, 1:4]), done,
               np.ascontiguousarray(out[:, O_SWEEP]), B, True)  # fmt: skip
    return len(done)


@nb.njit(cache=True, error_model="numpy", **_NO_CFUNC)
def _find_member_runs(bands, counts, member, min_bands, found):
    """Runs of at least ``min_bands`` neighbouring overlap-rejected bands of one train
    (``member``), cut into pieces of ``min_bands`` to ``2 min_bands - 1`` bands:
    ``found[m] = (pattern, row, first, last, train)``; returns their number."""
    m = 0
    for p in range(2):
        for r in range(counts.shape[1]):
            n = counts[p, r]
            k = 0
            while k < n:
                q = member[p, r, k]
                if q < 0 or bands[p, r, k, F_VALID] != BAND_OVERLAP:
                    k += 1
                    continue
                j = k
                while (j + 1 < n and member[p, r, j + 1] == q
                       and bands[p, r, j + 1, F_VALID] == BAND_OVERLAP):  # fmt: skip
                    j += 1
                # in pieces of min_bands (the last one takes the rest): the interval of a
                # long run changes along it (perspective, lens distortion), a stretch's must
                # not (as _find_tight_runs)
                for first in range(k, j - min_bands + 2, min_bands):
                    if m == found.shape[0]:
                        break
                    found[m, 0] = p
                    found[m, 1] = r
                    found[m, 2] = first
                    found[m, 3] = first + min_bands - 1 if j - first >= 2 * min_bands - 1 else j
                    found[m, 4] = q
                    m += 1
                k = j + 1
    return m


@nb.njit(cache=True, error_model="numpy", **_NO_CFUNC)
def _mark_runs(bands, pat, runs, done, sweep, B, spacing):
    """The measured runs' bands get their sweep, ``BAND_PERIODIC`` and, with ``spacing``,
    the run's spacing as their interval (bands valid alone keep their own, from their
    neighbours: on a tilted surface the spacing changes along a run)."""
    for q in done:
        p, r = pat[q], runs[q, 0]
        for k in range(runs[q, 1], runs[q, 2] + 1):
            bands[p, r, k, F_LENGTH] = sweep[q]
            if spacing:
                bands[p, r, k, F_INTERVAL] = B[q]
            bands[p, r, k, F_VALID] = BAND_PERIODIC


@nb.njit(cache=True, error_model="numpy", **_NO_CFUNC)
def _flood_trains(bands, counts, pat, runs, trains, B, pulse, tol, reach, passes, member,
                  lb, contradicted):
    """Mark as one train's pulses the bands linked to it across rows (the caller rejects them).

    A pulse train (bands swept past their neighbours, ``n >= 1``) whose rows show no clean
    gap a few intervals to either side has no floor to read ``n`` from: there its pulses
    pass the detector's tests as short bands of their own, and the sweep reads whole
    intervals short, a depth tens of centimetres off.  Where a row holds a measured
    train (``trains``, runs measured with ``n >= 1``), the rows above and below it carry
    the same train: from its bands, band links (the nearest centre in the next row,
    within ``reach`` intervals) and row neighbours (one interval apart) whose length and
    height are the linked pulse's within ``tol`` (and the train's within twice that)
    are its pulses too.  ``passes`` sweeps down and up the rows.  ``member[p, r, k]``
    gets the index into ``runs`` of the train of each band marked (-1 elsewhere).

    Where a link (to the next row, or along a row one interval on) reaches a band of a
    run measured with ``n = 0`` (``BAND_PERIODIC``) whose ``L / B`` differs from the
    train's (``lb``, per run) by more than :data:`CONTRADICTION_JUMP`,
    ``contradicted[q]`` of train ``q`` is counted up.
    """
    ref_len = np.full(member.shape, np.nan)
    ref_height = np.full(member.shape, np.nan)
    heights = np.empty(runs.shape[0])
    for q in trains:
        p, r = pat[q], runs[q, 0]
        heights[q] = _run_height(bands, p, runs[q])
        for k in range(runs[q, 1], runs[q, 2] + 1):
            member[p, r, k] = q
            ref_len[p, r, k] = pulse[q]
            ref_height[p, r, k] = heights[q]
        for side in range(2):  # along the row first, as _reject_continuations
            _walk_row(bands, counts, p, r, runs[q, 2] if side else runs[q, 1], 1 if side else -1,
                      q, B[q], pulse, heights, tol, member, ref_len, ref_height, lb,
                      contradicted)  # fmt: skip
    partner = np.empty(bands.shape[2], np.int64)
    rows = counts.shape[1]
    for _ in range(passes):
        for down in (True, False):
            for t in range(1, rows):
                o = t if down else rows - 1 - t  # the row to mark, from its neighbour r
                r = o - 1 if down else o + 1
                for p in range(2):
                    if counts[p, o] == 0 or counts[p, r] == 0:
                        continue
                    nearest_partners(bands[p], counts[p], o, r, reach, partner)
                    for k in range(counts[p, o]):
                        j = partner[k]
                        if j < 0 or member[p, o, k] >= 0 or member[p, r, j] < 0:
                            continue
                        q = member[p, r, j]
                        if _contradicts(bands[p, o, k], lb[q]):
                            contradicted[q] += 1
                            continue
                        if not _pulse_like(bands[p, o, k], ref_len[p, r, j], ref_height[p, r, j],
                                           pulse[q], heights[q], tol):  # fmt: skip
                            continue
                        member[p, o, k] = q
                        ref_len[p, o, k] = bands[p, o, k, F_LENGTH]
                        ref_height[p, o, k] = bands[p, o, k, F_HEIGHT]
                        for step in (-1, 1):
                            _walk_row(bands, counts, p, o, k, step, q, B[q], pulse, heights, tol,
                                      member, ref_len, ref_height, lb, contradicted)  # fmt: skip


@nb.njit(cache=True, error_model="numpy", **_INTERNAL)
def _run_height(bands, p, run):
    """The median height of the bands of ``run = (row, first, last)`` of pattern ``p``."""
    n = run[2] - run[1] + 1
    heights = np.empty(n)
    for i in range(n):
        heights[i] = bands[p, run[0], run[1] + i, F_HEIGHT]
    return median_in_place(heights, n)


@nb.njit(cache=True, error_model="numpy", **_INTERNAL)
def _pulse_like(band, length, height, train_length, train_height, tol):
    """Whether ``band`` (overlap-rejected or valid) is as long and high as a linked pulse
    (within ``tol``) and as its train's (within ``2 tol``)."""
    if not (band[F_VALID] == BAND_VALID or band[F_VALID] == BAND_OVERLAP):
        return False
    lb, hb = band[F_LENGTH], band[F_HEIGHT]
    return (abs(lb - length) <= tol * length and abs(hb - height) <= tol * height
            and abs(lb - train_length) <= 2.0 * tol * train_length
            and abs(hb - train_height) <= 2.0 * tol * train_height)  # fmt: skip


@nb.njit(cache=True, error_model="numpy", **_INTERNAL)
def _contradicts(band, lb):
    """Whether ``band`` was measured periodic with ``n = 0`` at an ``L / B`` more than
    :data:`CONTRADICTION_JUMP` from a train's ``lb``."""
    if band[F_VALID] != BAND_PERIODIC or not band[F_INTERVAL] > 0.0:
        return False
    own = band[F_LENGTH] / band[F_INTERVAL]
    return own < 1.0 and abs(own - lb) > CONTRADICTION_JUMP


@nb.njit(cache=True, error_model="numpy", **_INTERNAL)
def _walk_row(bands, counts, p, r, k, step, q, b, pulse, heights, tol, member, ref_len,
              ref_height, lb, contradicted):  # fmt: skip
    """From band ``k`` of row ``r`` along the row (``step``): the bands one interval ``b``
    apart (within ``tol``) and pulse-like become train ``q``'s, until the first that is not
    (which counts ``contradicted[q]`` up where it contradicts the train)."""
    prev = bands[p, r, k, F_CENTRE]
    i = k + step
    while 0 <= i < counts[p, r] and member[p, r, i] < 0:
        band = bands[p, r, i]
        spaced = abs(abs(band[F_CENTRE] - prev) - b) <= tol * b
        if spaced and _contradicts(band, lb[q]):
            contradicted[q] += 1
            break
        if not (spaced and _pulse_like(band, ref_len[p, r, i - step],
                                       ref_height[p, r, i - step], pulse[q], heights[q], tol)):
            break
        member[p, r, i] = q
        ref_len[p, r, i] = band[F_LENGTH]
        ref_height[p, r, i] = band[F_HEIGHT]
        prev = band[F_CENTRE]
        i += step


@nb.njit(cache=True, error_model="numpy", **_NO_CFUNC)
def _reject_continuations(bands, counts, pat, runs, done, B, pulse, tol):
    """Outwards from each end of the runs ``done``: the bands that continue their pulse
    train become ``BAND_OVERLAP`` (valid ones; the walk stops at the first that does not).

    A band continues it when it lies one interval ``B[q]`` (within ``tol`` of it) from the
    previous one and its length and height are the run's pulses' (``pulse[q]`` long, the
    median height of the run's bands, both within ``tol``): a band that only happens to
    be as long is ``L / (f B)`` (at least twice) as high.
    """
    for q in done:
        p, r = pat[q], runs[q, 0]
        height = _run_height(bands, p, runs[q])
        for side in range(2):
            step = 1 if side else -1
            k = runs[q, 2] + 1 if side else runs[q, 1] - 1
            prev = bands[p, r, k - step, F_CENTRE]
            while 0 <= k < counts[p, r]:
                b = bands[p, r, k]
                if not (abs(abs(b[F_CENTRE] - prev) - B[q]) <= tol * B[q]
                        and abs(b[F_LENGTH] - pulse[q]) <= tol * pulse[q]
                        and abs(b[F_HEIGHT] - height) <= tol * height):  # fmt: skip
                    break
                if b[F_VALID] == BAND_VALID:
                    b[F_VALID] = BAND_OVERLAP
                prev = b[F_CENTRE]
                k += step


def line_centred(bands: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """The bands with every centre on its line's trajectory centre.

    A pulse of a periodic run (``BAND_PERIODIC``) lies on the lines' trajectory
    centres when the integer part ``n`` of its ``L / B`` is even, and half-way between
    two of them when ``n`` is odd (see the module's docstring).  Such a pulse's centre
    is moved by half its interval (the run's spacing) onto the next line, so that a
    consumer of line positions (:mod:`.triangulation`) does not read it as a line of its
    own.  Its other fields are kept: its edges are still where its light is.

    Parameters
    ----------
    bands, counts : numpy.ndarray
        Both patterns' bands ``(2, R, max_bands, N_FIELDS)`` and counts ``(2, R)``, as
        :func:`measure_runs` left them.

    Returns
    -------
    numpy.ndarray
        ``bands`` itself when no pulse lies between lines, else a copy with their
        centres moved.
    """
    if not _odd_pulses(bands, counts, False):
        return bands
    out = bands.copy()
    _odd_pulses(out, counts, True)
    return out


@nb.njit(cache=True, error_model="numpy", **_NO_CFUNC)
def _odd_pulses(bands, counts, move):
    """Whether a periodic band has an odd ``n``; with ``move``, their centres moved."""
    found = False
    for p in range(counts.shape[0]):
        for r in range(counts.shape[1]):
            for k in range(counts[p, r]):
                b = bands[p, r, k]
                if b[F_VALID] != BAND_PERIODIC or not b[F_INTERVAL] > 0.0:
                    continue
                n = math.floor(b[F_LENGTH] / b[F_INTERVAL])
                if n % 2 == 1:
                    if not move:
                        return True
                    found = True
                    b[F_CENTRE] += 0.5 * b[F_INTERVAL]
    return found
