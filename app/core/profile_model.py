"""The band profile model: line box * motion box * Gaussian blur, and its inversion.

A band is ``box(L) * box(w) * gauss(sigma)`` (sweep, line width in camera
pixels, optics).  :mod:`lightflow.app.core.bands` measures two numbers per band,
both scale-free: the full width ``m`` at half of the band's plateau (the
plateau taken as the mean over the central half of a first half-maximum
width) and the ramp ``r`` from the 50 % to the 20 % level.  For long bands
``m == L`` exactly; when the sweep is not much longer than ``w + 4 sigma`` the
plateau is never reached and ``m`` overshoots.  This module tabulates
``m(L, w)`` and ``r(L, w)`` (unit sigma) from the exact profile (closed form
with the integrated normal CDF) and inverts them:

* :func:`fit_blur` finds the blur that makes every band's ramp consistent;
* :meth:`ProfileTables.true_length` recovers ``L`` from ``m`` given ``w`` and ``sigma``.

Everything is in units of sigma, so one table serves every rig.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import inspect
import math
import os
import sys
import threading

import numba as nb
import numpy as np

from . import bands as bands_module
from .bands import N_FIELDS, bands_in_row, sliding_mid

_INV_SQRT2 = 1.0 / math.sqrt(2.0)
_INV_SQRT2PI = 1.0 / math.sqrt(2.0 * math.pi)

#: table axes: blur sigma, line width and sweep in camera pixels
S_AXIS = np.arange(0.3, 2.7 + 1e-9, 0.15)
W_STEP = 0.5
W_AXIS = np.arange(0.0, 16.0 + 1e-9, W_STEP)
L_STEP = 0.5
L_AXIS = np.arange(0.0, 48.0 + 1e-9, L_STEP)
M_STEP = 0.25
M_AXIS = np.arange(0.0, 52.0 + 1e-9, M_STEP)
#: ramp axis of the joint inverse (camera px)
R_STEP = 0.1
R_AXIS = np.arange(0.0, 4.0 + 1e-9, R_STEP)
#: noise of a measured ramp relative to that of a measured width (the ramp averages
#: four crossings, two of them on the flatter foot of the edges)
RAMP_NOISE = 0.7
#: shortest sweep the joint inverse reports (a static line has no sweep to measure)
L_MIN = 0.5
PHASES = 4


@nb.njit(cache=True, inline="always")
def _G(t):
    """Antiderivative of the standard normal CDF: t Phi(t) + phi(t)."""
    return t * 0.5 * (1.0 + math.erf(t * _INV_SQRT2)) + math.exp(-0.5 * t * t) * _INV_SQRT2PI


@nb.njit(cache=True, inline="always")
def _H(t):
    """Antiderivative of _G: ((t^2 + 1) Phi(t) + t phi(t)) / 2."""
    return 0.5 * (
        (t * t + 1.0) * 0.5 * (1.0 + math.erf(t * _INV_SQRT2))
        + t * math.exp(-0.5 * t * t) * _INV_SQRT2PI
    )


@nb.njit(cache=True)
def profile(x, L, w):
    """Band profile at ``x`` (sigma = 1; plateau 1 for L > w): box(L) * box(w)/w * gauss(1)."""
    a = 0.5 * L
    b = 0.5 * max(w, 1e-3)
    return (_G(x + a + b) - _G(x + a - b) - _G(x - a + b) + _G(x - a - b)) / (2.0 * b)


@nb.njit(cache=True)
def pixel_value(d, L, w, sigma):
    """Pixel-integrated profile of a band centred ``d`` pixels away (camera px units)."""
    a = 0.5 * L
    b = 0.5 * max(w, 1e-3)
    s = sigma
    total = 0.0
    for sign, off in ((1.0, a + b), (-1.0, a - b), (-1.0, -a + b), (1.0, -a - b)):
        total += sign * (_H((d + 0.5 + off) / s) - _H((d - 0.5 + off) / s))
    return total * s * s / (2.0 * b)


@nb.njit(cache=False)  # calls into bands.py: numba's cache would not see its changes
def _simulate_detector(L, w, sigma, phase, out2):
    """Run the real band detector on three identical bands; (m, r) of the middle one."""
    # a static line (L = 0) is the limit of a tiny sweep: box(L) * box(w) has no area
    # at L = 0 itself, and the detector then measured noise-free nothing
    L = max(L, 1e-3)
    gap = 3.0 * w + 8.0 * sigma + 10.0
    B = L + gap
    n = int(3.0 * B + 40.0)
    x = np.empty(n)
    c0 = 20.0 + phase
    reach = 0.5 * (L + w) + 6.0 * sigma + 2.0
    for j in range(n):
        v = 0.0
        for k in range(3):
            d = j - (c0 + k * B)
            if abs(d) < reach:  # the profile is zero (to 1e-9) further out
                v += pixel_value(d, L, w, sigma)
        x[j] = 5.0 + 100.0 * v
    thr = np.empty((2, n))
    sliding_mid(x, int(2.2 * B) | 1, thr)
    out = np.empty((8, N_FIELDS))
    ns = bands_in_row(x, thr, 0.0, 100.0, 0.0, 1.0, out)
    out2[0] = np.nan
    out2[1] = np.nan
    for k in range(ns):
        if abs(out[k, 0] - (c0 + B)) < 0.5 * B:
            out2[0] = out[k, 1]
            out2[1] = out[k, 7]


# The table kernels below are serial over a range of (sigma, w) cells and
# release the GIL; _on_threads runs them on a thread per core.  numba's
# parallel=True would compile them several seconds slower, on the path to the
# first depth picture of a first run (the tables are built once per machine).


@nb.njit(cache=False, nogil=True)
def _measure_table(s_axis, w_axis, l_axis, m_out, r_out, lo, hi):
    nw, nl = w_axis.shape[0], l_axis.shape[0]
    for idx in range(lo, hi):
        i = idx // nw
        j = idx % nw
        tmp = np.empty(2)
        for k in range(nl):
            sm = 0.0
            sr = 0.0
            cnt = 0
            for p in range(PHASES):
                _simulate_detector(l_axis[k], w_axis[j], s_axis[i], p / PHASES, tmp)
                if np.isfinite(tmp[0]) and np.isfinite(tmp[1]):
                    sm += tmp[0]
                    sr += tmp[1]
                    cnt += 1
            m_out[i, j, k] = sm / cnt if cnt else np.nan
            r_out[i, j, k] = sr / cnt if cnt else np.nan


@nb.njit(cache=True, nogil=True)
def _invert_table(m_tab, l_axis, m_axis, out, lo, hi):
    """Per (sigma, w) cell ``lo .. hi``: L at each m of ``m_axis`` where m(L) informs."""
    nw, nl = m_tab.shape[1:]
    for idx in range(lo, hi):
        i = idx // nw
        j = idx % nw
        first = nl
        for k in range(nl - 1):
            a = m_tab[i, j, k]
            b = m_tab[i, j, k + 1]
            if np.isfinite(a) and np.isfinite(b) and (b - a) / (l_axis[k + 1] - l_axis[k]) > 0.5:
                first = k
                break
        for q in range(m_axis.shape[0]):
            out[i, j, q] = np.nan
            mv = m_axis[q]
            if first >= nl - 1 or mv < m_tab[i, j, first]:
                continue
            for k in range(first, nl - 1):
                a = m_tab[i, j, k]
                b = m_tab[i, j, k + 1]
                if a <= mv <= b and b > a:
                    out[i, j, q] = l_axis[k] + (mv - a) / (b - a) * (l_axis[k + 1] - l_axis[k])
                    break


@nb.njit(cache=True)
def _joint_cell(m_tab, r_tab, l_axis, m_axis, r_axis, rho, l_min, out, idx):
    """One (sigma, w) cell of :func:`_joint_table`."""
    nw, nl = m_tab.shape[1:]
    nm = m_axis.shape[0]
    nr = r_axis.shape[0]
    fine = 10
    i = idx // nw
    j = idx % nw
    # the model curve (m(L), r(L)) sampled finely (linear between table rows)
    k0 = 0
    while k0 < nl and l_axis[k0] < l_min:
        k0 += 1
    n = (nl - 1 - k0) * fine + 1
    cm = np.empty(n)
    cr = np.empty(n)
    cl = np.empty(n)
    for k in range(k0, nl - 1):
        for f in range(fine):
            q = (k - k0) * fine + f
            t = f / fine
            cm[q] = m_tab[i, j, k] + t * (m_tab[i, j, k + 1] - m_tab[i, j, k])
            cr[q] = r_tab[i, j, k] + t * (r_tab[i, j, k + 1] - r_tab[i, j, k])
            cl[q] = l_axis[k] + t * (l_axis[k + 1] - l_axis[k])
    cm[n - 1] = m_tab[i, j, nl - 1]
    cr[n - 1] = r_tab[i, j, nl - 1]
    cl[n - 1] = l_axis[nl - 1]
    inv_rho2 = 1.0 / (rho * rho)
    # the curve's points by m: for each m of the grid, only points nearer in
    # m than the worst best cost so far can win, so walk outwards from m and
    # stop there; ties go to the lowest index, as in a scan of every point
    nv = 0
    for q in range(n):
        if np.isfinite(cm[q]) and np.isfinite(cr[q]):
            nv += 1
    valid = np.empty(nv, np.int64)
    nv = 0
    for q in range(n):
        if np.isfinite(cm[q]) and np.isfinite(cr[q]):
            valid[nv] = q
            nv += 1
    # insertion sort (m(L) is nearly sorted already; numba's argsort and
    # searchsorted would cost seconds of compilation)
    order = valid
    for x in range(1, nv):
        q = order[x]
        y = x - 1
        while y >= 0 and cm[order[y]] > cm[q]:
            order[y + 1] = order[y]
            y -= 1
        order[y + 1] = q
    sorted_m = np.empty(nv)
    for x in range(nv):
        sorted_m[x] = cm[order[x]]
    best = np.empty(nr)
    bq = np.empty(nr, np.int64)
    for a in range(nm):
        mv = m_axis[a]
        for b in range(nr):
            best[b] = np.inf
            bq[b] = -1
        worst = np.inf
        lo = 0  # first point with m >= mv, by bisection
        hi = nv
        while lo < hi:
            mid = (lo + hi) // 2
            if sorted_m[mid] < mv:
                lo = mid + 1
            else:
                hi = mid
        lo = hi - 1
        while lo >= 0 or hi < nv:
            # the nearer side next: |mv - cm| never decreases along the walk
            if hi >= nv or (lo >= 0 and mv - sorted_m[lo] <= sorted_m[hi] - mv):
                q = order[lo]
                lo -= 1
            else:
                q = order[hi]
                hi += 1
            dm = mv - cm[q]
            if dm * dm > worst:
                break
            for b in range(nr):
                dr = r_axis[b] - cr[q]
                c = dm * dm + dr * dr * inv_rho2
                if c < best[b] or (c == best[b] and q < bq[b]):
                    best[b] = c
                    bq[b] = q
            worst = 0.0
            for b in range(nr):
                worst = max(worst, best[b])
        for b in range(nr):
            out[i, j, a, b] = cl[bq[b]] if bq[b] >= 0 else np.nan


@nb.njit(cache=True, nogil=True)
def _joint_table(m_tab, r_tab, l_axis, m_axis, r_axis, rho, l_min, out, lo, hi):
    """Per (sigma, w): the sweep that best explains a measured (width, ramp) pair.

    ``L = argmin (m - m(L))^2 + ((r - r(L)) / rho)^2``: long bands are decided by
    their width (their ramps are the line edge, whatever the sweep), bands not
    longer than the line by their ramps (their width is the line's), and bands
    in between by both.  NaN where the tables have no data.
    """
    for idx in range(lo, hi):
        _joint_cell(m_tab, r_tab, l_axis, m_axis, r_axis, rho, l_min, out, idx)


@nb.njit(cache=True, inline="always")
def joint_at(table, s_lo, s_step, w_step, m_step, r_step, sigma, w, m, r):
    """Sweep from (width ``m``, ramp ``r``) for ``sigma`` and line width ``w`` (4-linear).

    Sigma is clamped to the table; NaN when ``w``, ``m`` or ``r`` is outside it.
    """
    n0, n1, n2, n3 = table.shape
    a = min(max((sigma - s_lo) / s_step, 0.0), n0 - 1.0)
    b = w / w_step
    c = m / m_step
    d = min(max(r / r_step, 0.0), n3 - 1.0)
    if not (b >= 0.0 and c >= 0.0 and b <= n1 - 1 and c <= n2 - 1):
        return np.nan
    i = min(int(a), n0 - 2)
    j = min(int(b), n1 - 2)
    q = min(int(c), n2 - 2)
    e = min(int(d), n3 - 2)
    fa = a - i
    fb = b - j
    fc = c - q
    fd = d - e
    acc = 0.0
    for di in range(2):
        wa = fa if di else 1.0 - fa
        for dj in range(2):
            wb = fb if dj else 1.0 - fb
            for dq in range(2):
                wc = fc if dq else 1.0 - fc
                for de in range(2):
                    wd = fd if de else 1.0 - fd
                    acc += wa * wb * wc * wd * table[i + di, j + dj, q + dq, e + de]
    return acc


# the lookups of the blur fit are serial: a few thousand bands per call, and numba's
# parallel layer stalled for up to a second under load (once per blur refit, live)
@nb.njit(cache=True, nogil=True)
def _joint_many(table, s_lo, s_step, sigma, w, m, r, out):
    for k in range(m.shape[0]):
        out[k] = joint_at(table, s_lo, s_step, W_STEP, M_STEP, R_STEP, sigma[k], w[k], m[k], r[k])


@nb.njit(cache=True, inline="always")
def trilinear_at(table, lo0, st0, step1, step2, x0, x1, x2):
    """One trilinear lookup; axis 0 from ``lo0`` in steps ``st0`` (clamped), the others from 0."""
    n0, n1, n2 = table.shape
    a = min(max((x0 - lo0) / st0, 0.0), n0 - 1.0)
    b = x1 / step1
    c = x2 / step2
    if not (b >= 0.0 and c >= 0.0 and b <= n1 - 1 and c <= n2 - 1):
        return np.nan
    i = min(int(a), n0 - 2)
    j = min(int(b), n1 - 2)
    q = min(int(c), n2 - 2)
    fa = a - i
    fb = b - j
    fc = c - q
    acc = 0.0
    for di in range(2):
        wa = fa if di else 1.0 - fa
        for dj in range(2):
            wb = fb if dj else 1.0 - fb
            for dq in range(2):
                wc = fc if dq else 1.0 - fc
                acc += wa * wb * wc * table[i + di, j + dj, q + dq]
    return acc


@nb.njit(cache=True, nogil=True)
def _trilinear(table, ax0, step1, step2, x0, x1, x2, out):
    f0 = x0.ravel()
    f1 = x1.ravel()
    f2 = x2.ravel()
    res = out.ravel()
    for k in range(f0.shape[0]):
        res[k] = trilinear_at(table, ax0[0], ax0[1] - ax0[0], step1, step2, f0[k], f1[k], f2[k])


def tables_path():
    """Where the profile tables are cached (``pathlib.Path``): keyed by the detector's source."""
    from .depth_model import lut_cache_dir  # the same cache folder as the LUTs

    digest = hashlib.sha256(
        inspect.getsource(bands_module).encode()
        + inspect.getsource(sys.modules[__name__]).encode()
    ).hexdigest()[:12]
    return lut_cache_dir() / f"profile-tables-{digest}.npz"


@contextlib.contextmanager
def _build_lock(path):
    """An exclusive lock beside ``path`` (none when the folder is not writable)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle = open(path.with_name(path.name + ".lock"), "a")  # noqa: SIM115
    except OSError:
        yield
        return
    with handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def _on_threads(kernel, cells: int, *args) -> None:
    """Run ``kernel(*args, lo, hi)`` over cells ``0 .. cells`` in chunks, on a thread per core."""
    from concurrent.futures import ThreadPoolExecutor

    chunk = max(1, cells // 32)  # small chunks: the cells' costs differ
    threads = max(1, len(os.sched_getaffinity(0)))
    with ThreadPoolExecutor(threads, "profile-tables") as pool:
        jobs = [pool.submit(kernel, *args, lo, min(cells, lo + chunk))
                for lo in range(0, cells, chunk)]  # fmt: skip
        for job in jobs:
            job.result()


class ProfileTables:
    """What the band detector reports, m(sigma, w, L) and r(sigma, w, L), and L(sigma, w, m).

    Built by running the detector itself on exactly rendered, pixel-integrated
    bands at several sub-pixel phases, so that sampling and interpolation
    effects are part of the model.  Cached on disk (a few seconds to build).
    """

    def __init__(self, background: bool = False):
        self._ready = threading.Event()
        self._error: BaseException | None = None
        if background:
            # a daemon: a process that ends early must not wait for a build
            threading.Thread(target=self._prepare, name="profile-tables", daemon=True).start()
        else:
            self._prepare()
            self._wait()

    def _prepare(self) -> None:
        try:
            path = tables_path()
            if self._load(path):
                return
            # one process builds, the others wait for its file (a demo builds
            # them in a helper process while it compiles the pipeline)
            with _build_lock(path):
                if not self._load(path):
                    self._build(path)
        except BaseException as exc:  # noqa: BLE001 - raised where the tables are used
            self._error = exc
        finally:
            self._ready.set()

    def _wait(self) -> None:
        self._ready.wait()
        if self._error is not None:
            raise self._error

    # the arrays wait for a background load (see prefetch_tables)
    m = property(lambda self: self._array("_m"), doc="m(sigma, w, L): measured width.")
    r = property(lambda self: self._array("_r"), doc="r(sigma, w, L): measured ramp.")
    inverse = property(lambda self: self._array("_inverse"), doc="L(sigma, w, m).")
    joint = property(lambda self: self._array("_joint"), doc="L(sigma, w, m, r) (float32).")

    def _array(self, name: str) -> np.ndarray:
        self._wait()
        return getattr(self, name)

    def _load(self, path) -> bool:
        try:
            with np.load(path) as d:
                self._m, self._r, self._inverse = d["m"], d["r"], d["inverse"]
                self._joint = d["joint"]
            return True
        except (OSError, KeyError, ValueError):
            return False

    def _build(self, path) -> None:
        shape = (len(S_AXIS), len(W_AXIS), len(L_AXIS))
        m = np.empty(shape)
        r = np.empty(shape)
        cells = len(S_AXIS) * len(W_AXIS)
        _on_threads(_measure_table, cells, S_AXIS, W_AXIS, L_AXIS, m, r)
        inverse = np.empty((len(S_AXIS), len(W_AXIS), len(M_AXIS)))
        _on_threads(_invert_table, cells, m, L_AXIS, M_AXIS, inverse)
        joint = np.empty((len(S_AXIS), len(W_AXIS), len(M_AXIS), len(R_AXIS)), np.float32)
        _on_threads(_joint_table, cells, m, r, L_AXIS, M_AXIS, R_AXIS, RAMP_NOISE, L_MIN, joint)
        self._m, self._r, self._inverse, self._joint = m, r, inverse, joint
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(path.name + ".tmp.npz")
            np.savez(tmp, m=m, r=r, inverse=inverse, joint=joint)
            tmp.replace(path)
        except OSError:
            pass  # an unwritable cache only costs the rebuild

    @staticmethod
    def _lookup(table, step1, step2, sigma, a, b):
        shape = np.broadcast(sigma, a, b).shape
        out = np.empty(shape)
        args = [np.ascontiguousarray(np.broadcast_to(v, shape), dtype=np.float64)
                for v in (sigma, a, b)]  # fmt: skip
        _trilinear(table, S_AXIS, step1, step2, *args, out)
        return out

    def true_length(self, m, w, sigma) -> np.ndarray:
        """Sweep ``L`` from measured ``m``, line width ``w`` and blur ``sigma`` (camera px).

        NaN where the sweep is hidden in the line width and blur (static lines).
        """
        return self._lookup(self.inverse, W_STEP, M_STEP, sigma, w, m)

    def joint_length(self, m, r, w, sigma) -> np.ndarray:
        """Sweep ``L`` from the measured width ``m`` and ramp ``r`` together (camera px)."""
        shape = np.broadcast(m, r, w, sigma).shape
        args = [np.ascontiguousarray(np.broadcast_to(v, shape), dtype=np.float64).ravel()
                for v in (sigma, w, m, r)]  # fmt: skip
        out = np.empty(args[0].size)
        _joint_many(self.joint, S_AXIS[0], S_AXIS[1] - S_AXIS[0], *args, out)
        return out.reshape(shape)

    def measured_width(self, L, w, sigma) -> np.ndarray:
        """Forward model: the width at half height the detector reports."""
        return self._lookup(self.m, W_STEP, L_STEP, sigma, w, L)

    def ramp(self, L, w, sigma) -> np.ndarray:
        """Forward model: the 50->20 % ramp the detector reports (camera px)."""
        return self._lookup(self.r, W_STEP, L_STEP, sigma, w, L)


_TABLES: ProfileTables | None = None


def tables() -> ProfileTables:
    """The shared tables (loaded from the cache or built once)."""
    global _TABLES
    if _TABLES is None:
        _TABLES = ProfileTables()
    return _TABLES


def prefetch_tables() -> None:
    """Load (or build) the shared tables on a background thread from now on.

    :func:`tables` then returns at once, and the first use of their arrays
    waits for them, so that a pipeline can compile its band kernels meanwhile
    (``lightflow demo`` builds the tables in a helper process).
    """
    global _TABLES
    if _TABLES is None:
        _TABLES = ProfileTables(background=True)


def fit_blur(m, r, line, scale, slant=None, max_pixels: int = 4000, min_bands: int = 120):
    """Fit the blur model ``sigma^2 = a k^2 + b * scale^2`` to measured bands.

    Camera blur and pixel size (``a``) are fixed in camera pixels; projector
    defocus (``b``, in projector px^2) scales with the local magnification
    ``scale`` like the line width.  Along a row the camera blur of a line of
    slant ``s`` is wider by ``k = sqrt(1 + s^2)``.

    Every moving band is solved on its own first: the sigma at which the
    sweep its width implies (:meth:`ProfileTables.true_length`) also predicts
    its measured ramp.  Short bands (sweep within a few sigma of the line
    width) count as much as long ones — their ramps depend on the sweep, and
    the tables model that — so frames of short bands only (a fan at 1 ms, a
    ball at 5 ms) get their blur too.  A robust straight-line fit of the
    per-band sigma^2 against the magnification^2 then gives ``(a, b)``.

    Parameters
    ----------
    m, r, line, scale : numpy.ndarray
        Measured width at half height, ramp, line width (camera px) and
        magnification per pixel.
    slant : numpy.ndarray, optional
        Slant of the lines (columns per row).

    Returns
    -------
    (a, b) : tuple of float, or None when there are too few moving bands.
    """
    ok = np.isfinite(m) & np.isfinite(r) & np.isfinite(line) & np.isfinite(scale)
    ok &= m > line + 1.0  # moving: a static line's ramp says nothing about its sweep
    idx = np.flatnonzero(ok)
    if idx.size < min_bands:
        return None
    idx = idx[:: max(1, idx.size // max_pixels)]
    m, r, line, s2 = m.ravel()[idx], r.ravel()[idx], line.ravel()[idx], scale.ravel()[idx] ** 2
    k2 = np.ones_like(m) if slant is None else 1.0 + np.nan_to_num(slant.ravel()[idx]) ** 2
    t = tables()
    # per band: the sigma at which the sweep its width implies also predicts its ramp
    cols, sigma = _ramp_sigma(lambda sg: t.ramp(t.true_length(m, line, sg), line, sg) - r)
    if cols.size < min_bands // 2:
        return None
    # only bands whose width decides their sweep at that sigma: for a sweep within
    # the line width the width is the line's, and a smaller sigma would fake a sweep
    L = t.true_length(m[cols], line[cols], sigma)
    keep = L > line[cols] + 1.5 * sigma
    cols, sigma = cols[keep], sigma[keep]
    if cols.size < min_bands // 2:
        return None
    return blur_model(sigma**2, k2[cols], s2[cols])


def _ramp_sigma(mismatch):
    """Per band, the blur sigma where ``mismatch(sigma)`` (predicted minus measured ramp,
    an array over the bands) crosses zero; returns the bands that have one and it.

    The predicted ramp grows with sigma: the root is the first sign change to >= 0,
    found on a 0.05 px grid over the tables' sigma axis and interpolated linearly.
    """
    sig = np.arange(S_AXIS[0] + 0.05, S_AXIS[-1], 0.05)
    res = np.stack([mismatch(sg) for sg in sig])
    pos = np.isfinite(res) & (res >= 0)
    first = np.argmax(pos, axis=0)
    cols = np.flatnonzero(pos.any(axis=0) & (first > 0))
    j = first[cols]
    r0, r1 = res[j - 1, cols], res[j, cols]
    good = np.isfinite(r0) & (r1 > r0)
    cols, j, r0, r1 = cols[good], j[good], r0[good], r1[good]
    return cols, sig[j - 1] + (sig[j] - sig[j - 1]) * (-r0) / (r1 - r0)


def blur_model(sigma2, k2, s2) -> tuple[float, float]:
    """Robust least squares of ``sigma^2 = a k^2 + b s^2`` (Tukey reweighting).

    Parameters
    ----------
    sigma2 : numpy.ndarray
        Per band, the blur variance (camera px^2).
    k2, s2 : numpy.ndarray
        Per band, ``1 + slant^2`` and the magnification squared.

    Returns
    -------
    (a, b) : tuple of float
        ``b >= 0`` (a defocus cannot be negative); ``a`` clipped to the tables.
    """
    y, xa, xb = sigma2, k2, s2
    w = np.ones_like(y)
    a, b = float(np.median(y)), 0.0
    spread = np.ptp(xb) > 0.15 * np.mean(xb)
    for _ in range(10):
        if spread:
            A = np.stack([xa, xb], axis=1) * w[:, None]
            sol, *_ = np.linalg.lstsq(A, y * w, rcond=None)
            a, b = float(sol[0]), float(sol[1])
        else:
            a, b = float(np.sum(w * w * y * xa) / np.sum(w * w * xa * xa)), 0.0
        if b < 0.0:  # defocus cannot be negative: camera term only
            b = 0.0
            a = float(np.sum(w * w * y * xa) / np.sum(w * w * xa * xa))
        e = y - a * xa - b * xb
        scale_e = 1.4826 * float(np.median(np.abs(e))) + 1e-6
        u = e / (4.685 * scale_e)
        w = np.where(np.abs(u) < 1, 1 - u * u, 0.0)
    a = float(np.clip(a, 0.05, S_AXIS[-1] ** 2))
    return a, float(b)


def static_blur(m, r, line, scale, slant=None, min_bands: int = 200):
    """Fit the blur model on lines that stand still (a calibration: ``L = 0``).

    A static line's ramp depends on its width (known from the rig and the
    magnification) and the blur alone, so each line gives its sigma directly;
    lines seen at several depths (magnifications) separate the camera part
    ``a`` from the projector part ``b`` (:func:`blur_model`).

    Parameters
    ----------
    m, r, line, scale, slant : numpy.ndarray
        As in :func:`fit_blur`; bands wider than their line by more than a
        pixel (moving) are left out.
    min_bands : int

    Returns
    -------
    (a, b, n) : tuple, or None when fewer than ``min_bands`` static lines are seen
        ``n``: the number of lines (grid cells) used.
    """
    m, r, line, scale = (np.asarray(v, np.float64).ravel() for v in (m, r, line, scale))
    ok = np.isfinite(m) & np.isfinite(r) & np.isfinite(line) & np.isfinite(scale)
    ok &= (m < line + 1.0) & (line > 0.0)
    idx = np.flatnonzero(ok)
    if idx.size < min_bands:
        return None
    m, r, line, s2 = m[idx], r[idx], line[idx], scale[idx] ** 2
    k2 = np.ones_like(m) if slant is None else 1.0 + np.nan_to_num(np.ravel(slant)[idx]) ** 2
    t = tables()
    # per line: the sigma at which a line of no sweep has the measured ramp
    cols, sigma = _ramp_sigma(lambda sg: t.ramp(np.zeros_like(m), line, sg) - r)
    if cols.size < min_bands:
        return None
    a, b = blur_model(sigma**2, k2[cols], s2[cols])
    return a, b, int(cols.size)
