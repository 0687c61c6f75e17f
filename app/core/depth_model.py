"""Per-pixel depth model: the log flow ratio h_p(z) and its inverse (the LUT).

For a camera pixel with ray ``r`` (z = 1), the surface point is ``z * r``.
Projector i sees it at column ``u_i(z)`` (full OpenCV lens model), and its
pattern has a continuous line index ``k_i(u)`` (integers at the lines).  A
motion along the ray sweeps ``dk_i = k_i'(u_i) u_i'(z) dz``; the measured flow
in index units is band length / line interval.  The ratio of the two flows
removes ``dz``::

    h_p(z) = log |k_1'(u_1(z)) u_1'(z)| - log |k_2'(u_2(z)) u_2'(z)|

Working in projector pixels makes the paper's ``f2/f1`` conversion part of h.
For a single projector with the exp2 pair, ``u_1 = u_2`` and ``u'`` cancels:
``h_p(z) = log(P_2(u) / P_1(u))``, the log ratio of the local pitches, which the
camera sees as the ratio of the apparent line intervals ``B_2 / B_1``.

The LUT stores, per pixel of the analysis grid, ``z`` at ``M`` uniform steps of
``h`` over the longest monotonic stretch of h_p on the working depth range;
lookup is one fused, vectorised pass (:func:`lookup_depth`).
"""

from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numba as nb
import numpy as np

from .errors import ConfigError
from .geometry import LENS_COEFFICIENTS, camera_rays, lens_coefficients, lens_distort_derivative
from .patterns import pattern_code, pitch_at
from .rig import Rig
from .threads import run_rows

#: 5: the tilted-sensor lens terms are applied (tables of tilted rigs changed)
LUT_VERSION = 5
#: inverse-depth samples per pixel in the LUT (96 bytes/pixel with the two scalars: 184 MB
#: at 1600x1200 with stride 1)
LUT_SAMPLES = 22
#: forward samples of h(z) used to find the monotonic stretch
FORWARD_SAMPLES = 96


@dataclass(frozen=True)
class DepthRange:
    """Working depth range (metres) over which h_p(z) is inverted."""

    near: float = 0.3
    far: float = 3.0

    def __post_init__(self):
        if not 0 < self.near < self.far:
            raise ConfigError(f"depth range: expected 0 < near < far, got {self.near}, {self.far}")


# ---------------------------------------------------------------- pattern coding for numba


def pattern_params(rig: Rig) -> np.ndarray:
    """Per pattern: [proj index, kind code, pitch or exp2 step, projector width].

    Kind code and step are :func:`lightflow.app.core.patterns.pattern_code`, read by
    :func:`lightflow.app.core.patterns.pitch_at`.
    """
    rows = []
    for pi, proj in enumerate(rig.projectors):
        for pat in proj.patterns:
            code, step = pattern_code(pat)
            rows.append([pi, code, step, proj.width])
    return np.array(rows, dtype=np.float64)


def projector_params(rig: Rig) -> np.ndarray:
    """Per projector: R (9), t (3), fx, skew, cx, fy, cy, then :func:`lens_coefficients`."""
    out = np.zeros((len(rig.projectors), 17 + LENS_COEFFICIENTS))
    for i, p in enumerate(rig.projectors):
        out[i, :9] = p.R.ravel()
        out[i, 9:12] = p.t
        out[i, 12:17] = [p.K[0, 0], p.K[0, 1], p.K[0, 2], p.K[1, 1], p.K[1, 2]]
        out[i, 17:] = lens_coefficients(p.dist)
    return out


@nb.njit(cache=True, error_model="numpy", inline="always", no_cfunc_wrapper=True)
def proj_u_du(pp, x, y, z):
    """Projector column u and du/dz for the camera point z * (x, y, 1)."""
    # camera point and its derivative along the ray
    X = pp[0] * x + pp[1] * y + pp[2]
    Y = pp[3] * x + pp[4] * y + pp[5]
    Z = pp[6] * x + pp[7] * y + pp[8]
    px = z * X + pp[9]
    py = z * Y + pp[10]
    pz = z * Z + pp[11]
    xn = px / pz
    yn = py / pz
    dxn = (X * pz - Z * px) / (pz * pz)
    dyn = (Y * pz - Z * py) / (pz * pz)
    xd, yd, dxd, dyd = lens_distort_derivative(pp[17:], xn, yn, dxn, dyn)
    u = pp[12] * xd + pp[13] * yd + pp[14]
    du = pp[12] * dxd + pp[13] * dyd
    return u, du, pz


@nb.njit(cache=True, error_model="numpy", no_cfunc_wrapper=True, no_cpython_wrapper=True)
def _h_of_z(projs, pats, single, x, y, z):
    """h_p(z) = log|dk1/dz| - log|dk2/dz|; NaN where a projector cannot see the point."""
    u1, du1, pz1 = proj_u_du(projs[int(pats[0, 0])], x, y, z)
    u2, du2, pz2 = proj_u_du(projs[int(pats[1, 0])], x, y, z)
    if pz1 <= 0.0 or pz2 <= 0.0:
        return np.nan
    p1 = pitch_at(int(pats[0, 1]), pats[0, 2], pats[0, 3], u1)
    p2 = pitch_at(int(pats[1, 1]), pats[1, 2], pats[1, 3], u2)
    if p1 <= 0.0 or p2 <= 0.0:
        return np.nan
    if single:
        return math.log(p2 / p1)
    if du1 == 0.0 or du2 == 0.0:
        return np.nan
    return math.log(abs(du1) / p1) - math.log(abs(du2) / p2)


# serial and releasing the GIL, run on a thread per core by build_lut: numba's
# parallel=True compiles about 1.5x slower (seconds on a cold cache, on the
# path to a first run's first depth picture) for no faster a build
@nb.njit(cache=True, error_model="numpy", nogil=True, no_cfunc_wrapper=True)
def _build_lut(rays, projs, pats, single, near, far, n_fwd, n_lut, min_slope, h0, inv_dh, table):
    n = rays.shape[0]
    inv_near = 1.0 / near
    inv_far = 1.0 / far
    hs = np.empty(n_fwd)
    zs = np.empty(n_fwd)
    for i in range(n):
        x = rays[i, 0]
        y = rays[i, 1]
        for j in range(n_fwd):
            zs[j] = 1.0 / (inv_near + (inv_far - inv_near) * j / (n_fwd - 1))
            hs[j] = _h_of_z(projs, pats, single, x, y, zs[j])
        # longest stretch where h is finite and strictly monotonic with |dh/dz| >= min_slope
        best_s = 0
        best_len = 0
        run_s = 0
        run_len = 0
        run_sign = 0
        for j in range(n_fwd - 1):
            d = hs[j + 1] - hs[j]
            ok = np.isfinite(d) and abs(d) >= min_slope * (zs[j + 1] - zs[j])
            sign = 1 if d > 0 else -1
            if ok and run_len > 0 and sign == run_sign:
                run_len += 1
            elif ok:
                run_s = j
                run_len = 1
                run_sign = sign
            else:
                run_len = 0
            if run_len > best_len:
                best_len = run_len
                best_s = run_s
        if best_len < 4:
            h0[i] = np.nan
            inv_dh[i] = 0.0
            for m in range(n_lut):
                table[i, m] = np.nan
            continue
        a = best_s
        b = best_s + best_len
        ha = hs[a]
        hb = hs[b]
        lo = min(ha, hb)
        hi = max(ha, hb)
        dh = (hi - lo) / (n_lut - 1)
        h0[i] = lo
        inv_dh[i] = 1.0 / dh
        # invert: bracket in the forward samples, then refine by secant/bisection on h(z)
        for m in range(n_lut):
            target = lo + dh * m
            # find bracket j with target between hs[j], hs[j+1]
            jj = a
            for j in range(a, b):
                if (hs[j] - target) * (hs[j + 1] - target) <= 0.0:
                    jj = j
                    break
            za = zs[jj]
            zb = zs[jj + 1]
            fa = hs[jj] - target
            fb = hs[jj + 1] - target
            z = za
            for _ in range(40):
                if fb == fa:
                    break
                z = zb - fb * (zb - za) / (fb - fa)
                if not (min(za, zb) <= z <= max(za, zb)):
                    z = 0.5 * (za + zb)
                fz = _h_of_z(projs, pats, single, x, y, z) - target
                if abs(fz) < 1e-12:
                    break
                if fz * fa < 0.0:
                    zb = z
                    fb = fz
                else:
                    za = z
                    fa = fz
            table[i, m] = 1.0 / z


@dataclass
class DepthLUT:
    """Inverse of h_p per grid pixel: ``z`` at ``LUT_SAMPLES`` uniform steps of h.

    Attributes
    ----------
    stride : int
        Grid stride in camera pixels (1 = every pixel).
    h0, inv_dh : numpy.ndarray
        ``(h, w)`` float32: first h of the table and 1 / step (0 where unusable).
    table : numpy.ndarray
        ``(h, w, M)`` float32 inverse depths 1/z (smoother in h than z); a view of
        :attr:`planes`.
    planes : numpy.ndarray
        The same values sample-major, ``(M, h, w)`` (made from ``table``): what the
        lookup reads.  A smooth surface reads the same few samples over many
        neighbouring pixels, so the lookup streams about 4 of the M planes instead
        of every pixel's whole row (0.9 -> 0.6 ms per lookup on a board).
    """

    stride: int
    h0: np.ndarray
    inv_dh: np.ndarray
    table: np.ndarray
    planes: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        # one copy of the samples (184 MB at stride 1): ``table`` becomes a view of it
        self.planes = np.ascontiguousarray(np.moveaxis(self.table, 2, 0))
        self.table = np.moveaxis(self.planes, 0, 2)

    @property
    def nbytes(self) -> int:
        return self.h0.nbytes + self.inv_dh.nbytes + self.table.nbytes

    @property
    def usable(self) -> np.ndarray:
        return self.inv_dh > 0


def h_function(rig: Rig, rays_xy: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Evaluate h_p(z) for rays ``(n, 2)`` (normalised x, y) at depths ``z`` ``(n,)``.

    Returns NaN where a projector cannot see the point.
    """
    projs, pats = projector_params(rig), pattern_params(rig)
    return _h_many(projs, pats, rig.single_projector, rays_xy, np.broadcast_to(z, len(rays_xy)))


@nb.njit(cache=True, error_model="numpy", no_cfunc_wrapper=True)
def _h_many(projs, pats, single, xy, z):
    out = np.empty(xy.shape[0])
    for i in range(xy.shape[0]):
        out[i] = _h_of_z(projs, pats, single, xy[i, 0], xy[i, 1], z[i])
    return out


def build_lut(
    rig: Rig,
    stride: int = 2,
    depth_range: DepthRange = DepthRange(),
    min_slope: float = 0.02,
    progress=None,
) -> DepthLUT:
    """Tabulate the inverse of h_p(z) for every grid pixel.

    Parameters
    ----------
    rig : Rig
    stride : int
        Analysis grid stride (every ``stride``-th row and column).
    depth_range : DepthRange
        Depths over which h is inverted.
    min_slope : float
        Smallest usable |dh/dz| in 1/m; flatter stretches are not invertible.
    progress : callable, optional
        Called with ``(done_rows, total_rows)``.
    """
    rays = camera_rays(rig.camera, stride)
    gh, gw = rays.shape[:2]
    flat = np.ascontiguousarray(rays[..., :2].reshape(-1, 2))
    n = flat.shape[0]
    h0 = np.empty(n)
    inv_dh = np.empty(n)
    table = np.empty((n, LUT_SAMPLES))
    projs, pats = projector_params(rig), pattern_params(rig)
    chunk = max(gw, (n // 20 // gw) * gw)

    def build(s: int) -> int:
        e = min(n, s + chunk)
        _build_lut(
            flat[s:e], projs, pats, rig.single_projector, depth_range.near, depth_range.far,
            FORWARD_SAMPLES, LUT_SAMPLES, min_slope, h0[s:e], inv_dh[s:e], table[s:e],
        )  # fmt: skip
        return e

    # chunks of grid rows on a thread per core (the kernel releases the GIL)
    with ThreadPoolExecutor(max(1, len(os.sched_getaffinity(0))), "lut") as pool:
        for e in pool.map(build, range(0, n, chunk)):
            if progress:
                progress(e // gw, gh)
    return DepthLUT(
        stride,
        h0.reshape(gh, gw).astype(np.float32),
        inv_dh.reshape(gh, gw).astype(np.float32),
        table.reshape(gh, gw, LUT_SAMPLES).astype(np.float32),
    )


def lut_cache_dir() -> Path:
    base = os.environ.get("LIGHTFLOW_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "lightflow"
    )
    return Path(base)


def load_or_build_lut(
    rig: Rig, stride: int = 2, depth_range: DepthRange = DepthRange(), progress=None
) -> DepthLUT:
    """The LUT for this rig from the on-disk cache, building (and caching) it when absent.

    The cache key hashes the rig's geometry, the stride, the depth range and the LUT version.
    """
    near, far = depth_range.near, depth_range.far
    key = f"{rig.geometry_digest()}-s{stride}-{near:g}-{far:g}-v{LUT_VERSION}"
    path = lut_cache_dir() / f"lut-{key}.npz"
    if path.exists():
        try:
            with np.load(path) as d:
                return DepthLUT(stride, d["h0"], d["inv_dh"], d["table"])
        except (OSError, ValueError, KeyError):
            pass  # a damaged cache entry is rebuilt below
    lut = build_lut(rig, stride, depth_range, progress=progress)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + f".{os.getpid()}.tmp.npz")
        np.savez(tmp, h0=lut.h0, inv_dh=lut.inv_dh, table=lut.table)
        tmp.replace(path)
    except OSError:
        pass  # caching is an optimisation; a read-only home must not stop a scan
    return lut


@nb.njit(cache=True, error_model="numpy", inline="always", no_cfunc_wrapper=True)
def _spline_at(planes, i, j, t):
    """Catmull-Rom through the uniform samples ``planes[:, i, j]`` (clamped ends) at ``t``.

    Returns the value and its derivative in ``t``.
    """
    m = planes.shape[0]
    j1 = min(int(t), m - 2)
    f = t - j1
    p1 = planes[j1, i, j]
    p2 = planes[j1 + 1, i, j]
    p0 = planes[j1 - 1, i, j] if j1 > 0 else 2 * p1 - p2
    p3 = planes[j1 + 2, i, j] if j1 + 2 < m else 2 * p2 - p1
    a = p2 - p0
    b = 2 * p0 - 5 * p1 + 4 * p2 - p3
    c = 3 * (p1 - p2) + p3 - p0
    return p1 + 0.5 * f * (a + f * (b + f * c)), 0.5 * (a + f * (2.0 * b + 3.0 * f * c))


@nb.njit(cache=True, error_model="numpy", nogil=True, no_cfunc_wrapper=True)
def _lookup(logr, bits, before, h0, inv_dh, planes, z, slope, i0, i1):
    """Depth at ``logr`` on grid rows ``i0 .. i1``; also ``|dz / dlogr|`` unless
    ``slope`` is empty (``planes``: :attr:`DepthLUT.planes`).  Each pixel's samples are
    read once.  Unless ``before`` is empty, only the pixels whose log ratio's bits
    (``bits``, ``logr`` as int32) differ from it."""
    gw = logr.shape[1]
    m = planes.shape[0]
    want_slope = slope.size > 0
    only_changed = before.size > 0
    for i in range(i0, i1):
        for j in range(gw):
            if only_changed and bits[i, j] == before[i, j]:
                continue
            k = inv_dh[i, j]
            h = logr[i, j]
            z[i, j] = np.nan
            if want_slope:
                slope[i, j] = np.nan
            if not (k > 0.0) or not np.isfinite(h):
                continue
            t = (h - h0[i, j]) * k
            if t < 0.0 or t > m - 1:
                continue
            inv_z, d_inv_z = _spline_at(planes, i, j, t)
            zz = 1.0 / inv_z
            z[i, j] = zz
            if want_slope:
                slope[i, j] = abs(d_inv_z * k) * zz * zz


def depth_and_slope(lut: DepthLUT, log_ratio: np.ndarray):
    """Depth (metres) and ``|dz / dlog_ratio|`` per grid pixel; NaN outside the LUT.

    The depth is :func:`lookup_depth`'s; the slope is the derivative of the
    same interpolating spline, for the predicted error of each pixel.

    Parameters
    ----------
    lut : DepthLUT
    log_ratio : numpy.ndarray
        ``(h, w)`` log flow ratios.

    Returns
    -------
    (numpy.ndarray, numpy.ndarray)
        ``(h, w)`` float32 depth and slope (metres per unit of log ratio).
    """
    return _run_lookup(lut, log_ratio, with_slope=True)


def update_depth_and_slope(lut: DepthLUT, log_ratio: np.ndarray, before: np.ndarray,
                           depth: np.ndarray, slope: np.ndarray) -> None:  # fmt: skip
    """:func:`depth_and_slope` of ``log_ratio`` into ``depth`` and ``slope``, which hold those
    of ``before``: only the pixels whose log ratio changed are looked up again.

    Parameters
    ----------
    lut : DepthLUT
    log_ratio, before : numpy.ndarray
        ``(h, w)`` float32 log flow ratios, now and when ``depth`` and ``slope`` were
        looked up (pixels compared bit for bit).
    depth, slope : numpy.ndarray
        ``(h, w)`` float32, updated in place.
    """
    logr = log_ratio.astype(np.float32, copy=False)
    old = before.astype(np.float32, copy=False).view(np.int32)
    run_rows(_lookup, logr.shape[0], logr, logr.view(np.int32), old, lut.h0, lut.inv_dh,
             lut.planes, depth, slope)  # fmt: skip


def lookup_depth(lut: DepthLUT, log_ratio: np.ndarray) -> np.ndarray:
    """Depth ``z`` (metres) for a grid map of measured log flow ratios; NaN outside the LUT.

    Parameters
    ----------
    lut : DepthLUT
    log_ratio : numpy.ndarray
        ``(h, w)`` log flow ratios.

    Returns
    -------
    numpy.ndarray
        ``(h, w)`` float32.
    """
    return _run_lookup(lut, log_ratio, with_slope=False)


def _run_lookup(lut: DepthLUT, log_ratio: np.ndarray, with_slope: bool):
    logr = log_ratio.astype(np.float32, copy=False)
    z = np.empty(logr.shape, np.float32)
    slope = np.empty(logr.shape if with_slope else (0, 0), np.float32)
    # bands of grid rows on a thread per core (the kernel releases the GIL)
    every = np.empty((0, 0), np.int32)
    run_rows(_lookup, logr.shape[0], logr, every, every, lut.h0, lut.inv_dh, lut.planes, z,
             slope)  # fmt: skip
    return (z, slope) if with_slope else z
