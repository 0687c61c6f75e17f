"""The sparse pattern's line interval, predicted from the dense pattern and the rig.

A flow is a sweep over the local line interval, ``L / B``.  The interval is
measured from the neighbouring lines, a whole interval away on each side.  On
a curved object (a ball) the lines of a sparse pattern (60-90 camera px
apart) bunch up towards the limb, and the mean spacing to the neighbours is
several per cent shorter than the interval at the band: the flow comes out
that much too long, and the depth tens of millimetres off.

The two patterns see the same surface.  Along a camera row the surface point
moves by ``dX/dx = z r_x + (dz/dx) r`` per camera pixel (``r`` the pixel's
ray), and pattern ``i``'s projector column by ``du_i/dx = A_i(z) + (dz/dx)
C_i(z)``, with ``A_i`` its change at a fixed depth and ``C_i = du_i/dz`` along
the ray, both known from the rig.  The dense pattern's interval ``B_d =
P_d / |du_d/dx|`` fixes ``dz/dx``; that predicts the sparse pattern's interval
``B_s = P_s / |du_s/dx|``, from lines a few pixels away instead of a whole
sparse interval.  Where the measured and predicted intervals of the sparse
pattern disagree by more than :data:`DISAGREE_LOG`, the prediction is used, and
the sweeps are read again with it (:meth:`FlowModel.reread`: the interval also
sets the line's width that a short sweep is read against).  The prediction
needs the depth, which comes from the flows the measured interval biases: it is
made only where a depth off by :data:`DEPTH_TOLERANCE` would not move it by more
than that tolerance, else a biased depth would hold the correction where the
bias put it.

Two projectors with uniform patterns only (with one projector the intervals
themselves are the measurement).
"""

from __future__ import annotations

import math

import cv2
import numba as nb
import numpy as np

from .depth_model import DepthRange
from .geometry import project_to_projector, undistort_pixels
from .kernel_options import INTERNAL, NO_CFUNC
from .rig import Rig
from .threads import run_rows

#: depth samples of the A, C tables (uniform in 1/z over the working range)
N_DEPTHS = 24
#: the dense pattern's lines must be at least this many times closer than the sparse
#: one's for its interval to predict the other's
DENSER = 2.0
#: relative bend of the dense intervals over the sparse reach that marks a curved
#: surface (planes show none; chosen on the tuning rigs)
CURVED = 0.005
#: Gaussian sigma (grid cells) over which the disagreement is averaged
SMOOTH_CELLS = 2.0
#: the tables are computed on every COARSE-th grid cell and interpolated between
#: (projections are smooth across the image: 3e-4 relative error; a build of 0.05 s)
COARSE = 8
#: |log(measured / predicted interval)| of the sparse pattern above which the
#: prediction replaces the measurement (the prediction's own error is 1-2 %;
#: chosen on the tuning rigs of the evaluation matrix)
DISAGREE_LOG = 0.03
#: a cell takes the averaged disagreement when the cells around it that have a
#: prediction weigh at least this much in the average (not only the cells with one:
#: the sweeps are read again with the corrected interval and averaged over a few cells,
#: and a correction with holes would mix corrected and uncorrected sweeps; chosen on
#: the tuning rigs)
NEAR_WEIGHT = 0.3
#: the relative depth error a pixel that keeps its depth may have (the pipeline's
#: ``max_depth_std``): the prediction needs the depth, and where a depth off by this
#: much either way moves it by more than :data:`DISAGREE_LOG`, it is not made
DEPTH_TOLERANCE = 0.05


class IntervalModel:
    """Tables ``A_i(z)``, ``C_i(z)`` on a coarse grid over the image, for a two-projector rig.

    Parameters
    ----------
    rig : Rig
        Two projectors with uniform patterns.
    stride : int
        Analysis grid stride.
    depth_range : DepthRange
    """

    def __init__(self, rig: Rig, stride: int, depth_range: DepthRange):
        cam = rig.camera
        self.stride = stride
        gh, gw = cam.height // stride, cam.width // stride
        # every COARSE-th analysis cell, one sample past the last cell on each axis
        ch, cw = (gh - 1) // COARSE + 2, (gw - 1) // COARSE + 2
        off = 0.5 * (stride - 1)
        xs = np.arange(cw) * COARSE * stride + off
        ys = np.arange(ch) * COARSE * stride + off
        px = np.stack(np.meshgrid(xs, ys), axis=-1)

        def rays(pixels):
            xy = undistort_pixels(cam.K, cam.dist, pixels)
            return np.concatenate([xy, np.ones((ch, cw, 1))], axis=-1)

        ray = rays(px)
        ray_x = rays(px + [0.5, 0.0]) - rays(px - [0.5, 0.0])
        self.inv_z0 = 1.0 / depth_range.far
        self.inv_z_step = (1.0 / depth_range.near - self.inv_z0) / (N_DEPTHS - 1)
        self.pitch = np.array([pat.pitch_px for _, pat in rig.patterns])
        z = 1.0 / (self.inv_z0 + np.arange(N_DEPTHS) * self.inv_z_step)
        z = z[:, None, None, None]  # all depths in one projection
        dz = 1e-4 * z
        #: (pattern, depth, coarse row, coarse col): du/dx at a fixed depth (per camera
        #: px), and du/dz along the ray (per metre)
        self.a = np.empty((2, N_DEPTHS, ch, cw))
        self.c = np.empty((2, N_DEPTHS, ch, cw))
        for p, (proj, _pat) in enumerate(rig.patterns):
            # central differences: half a pixel and a small depth step either way
            self.a[p] = (project_to_projector(proj, z * (ray + 0.5 * ray_x))[..., 0]
                         - project_to_projector(proj, z * (ray - 0.5 * ray_x))[..., 0])  # fmt: skip
            self.c[p] = (project_to_projector(proj, (z + dz) * ray)[..., 0]
                         - project_to_projector(proj, (z - dz) * ray)[..., 0]) / (2 * dz[..., 0])

    def curved(self, intervals: np.ndarray) -> np.ndarray:
        """Per grid cell, whether the surface bends over the sparse pattern's reach.

        There the sparse pattern's measured interval (the mean spacing to its
        neighbours) is biased, and with it a depth from the intervals.

        Parameters
        ----------
        intervals : numpy.ndarray
            ``(2, h, w)`` measured line intervals (camera px).

        Returns
        -------
        numpy.ndarray
            ``(h, w)`` bool.
        """
        # which pattern is the sparse one, from a quarter of the cells (that is enough)
        sample = intervals[:, ::2, ::2]
        both = np.isfinite(sample).all(axis=0)
        if np.count_nonzero(both) < 16:
            return np.zeros(intervals.shape[1:], bool)
        # one pattern at a time: indexing both at once with the mask cost more than the
        # medians (0.4 -> 0.27 ms; the same values)
        med = [np.median(sample[p][both]) for p in range(2)]
        sparse = int(med[1] > med[0])
        return self._curved(intervals, sparse, float(med[sparse]))

    def correct(self, intervals: np.ndarray, depth: np.ndarray,
                curved: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
        """Per grid cell, the sparse pattern's ``log(measured / predicted)`` interval.

        Parameters
        ----------
        intervals : numpy.ndarray
            ``(2, h, w)`` measured line intervals (camera px).
        depth : numpy.ndarray
            ``(h, w)`` depth estimate (m) to evaluate the geometry at.
        curved : numpy.ndarray, optional
            :meth:`curved` of ``intervals``, when the caller has it already.

        Returns
        -------
        numpy.ndarray
            ``(2, h, w)`` float32: per pattern, the log of the factor its flow is to
            be multiplied by (``log(B_measured / B_predicted)``); 0 where the
            measurement stands (agreement, no prediction, or the dense pattern).
        """
        out = np.zeros((2, *depth.shape), np.float32)
        if curved is None:
            curved = self.curved(intervals)
        if not curved.any():
            return out  # a plane (or a gentle curve): every measured interval stands
        lg, have = self.disagreement(intervals, np.where(curved, depth, np.nan))
        # a curved surface biases the measured interval smoothly over a band's reach;
        # the dense interval's noise, amplified in the prediction, is not smooth: the
        # disagreement is averaged over a few cells before it is judged
        for p in range(2):  # the sparse pattern of each cell (mostly one pattern)
            if not have[p].any():
                continue
            # the weights' blur serves the mean and the test of what is near (once)
            weight = cv2.GaussianBlur(have[p], (0, 0), SMOOTH_CELLS)
            mean = _local_mean(lg[p], have[p], weight)
            # soft: the part beyond the tolerance, so the correction has no step where
            # the disagreement crosses it (a step reads as an outlier to the smoothing)
            soft = np.sign(mean) * np.maximum(np.abs(mean) - DISAGREE_LOG, 0.0)
            near = weight >= NEAR_WEIGHT
            out[p] = np.where(near & np.isfinite(intervals[p]), soft, 0.0)
        return out

    def disagreement(self, intervals: np.ndarray, depth: np.ndarray):
        """Per grid cell, ``log(measured / predicted)`` interval of the sparse pattern.

        Parameters
        ----------
        intervals : numpy.ndarray
            ``(2, h, w)`` measured line intervals (camera px).
        depth : numpy.ndarray
            ``(h, w)`` depth (m).

        Returns
        -------
        (numpy.ndarray, numpy.ndarray)
            ``(2, h, w)`` float32 log ratios (0 for the dense pattern), and 1 where a
            prediction was made (the sparse pattern of a cell with both intervals and
            a depth in range), else 0.
        """
        lg = np.zeros((2, *depth.shape), np.float32)
        have = np.zeros((2, *depth.shape), np.float32)
        run_rows(_disagreement, depth.shape[0], intervals, depth, self.a, self.c, self.pitch,
                 self.inv_z0, self.inv_z_step, COARSE, DENSER, DEPTH_TOLERANCE, DISAGREE_LOG,
                 lg, have)  # fmt: skip
        return lg, have

    def depth(self, intervals: np.ndarray, where: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
        """Per grid cell, the depth that the two patterns' line intervals alone give.

        Along a row, pattern ``i``'s interval is ``P_i / |A_i(z) + (dz/dx) C_i(z)|``:
        two intervals, two unknowns.  For each depth of the tables the first
        pattern's interval fixes ``dz/dx`` and predicts the second's; the depth is
        where the prediction meets the measurement.  No motion is needed, so it
        serves cells whose lines move too little for a flow (a fan near its hub).

        Parameters
        ----------
        intervals : numpy.ndarray
            ``(2, h, w)`` measured line intervals (camera px).
        where : numpy.ndarray, optional
            ``(h, w)`` bool: only these cells (NaN elsewhere); default all.

        Returns
        -------
        (numpy.ndarray, numpy.ndarray)
            ``(h, w)`` float32 depth (m) and the sensitivity ``|d log(B_1 / B_0) /
            d log z|`` there (an interval ratio off by ``e`` moves the log depth by
            ``e`` over it); NaN where the intervals are missing, where no depth of
            the working range, or more than one, explains them.
        """
        h, w = intervals.shape[1:]
        z = np.empty((h, w), np.float32)
        sens = np.empty((h, w), np.float32)
        if where is None:
            where = np.ones((h, w), np.bool_)
        run_rows(_interval_depth, h, intervals, where, self.a, self.c, self.pitch, self.inv_z0,
                 self.inv_z_step, COARSE, z, sens)  # fmt: skip
        return z, sens

    def _curved(self, intervals: np.ndarray, sparse: int, sparse_interval: float) -> np.ndarray:
        """Where the dense pattern's intervals bend over the sparse pattern's reach.

        The sparse interval is the mean spacing to the neighbours, half a sparse
        interval ``h`` either side: it is off by about ``(B(x - h) + B(x + h)) / 2 -
        B(x)``.  On a plane the intervals change linearly and that is 0; where the
        dense pattern shows it above :data:`CURVED`, the surface bends.
        """
        dense = intervals[1 - sparse]
        values = np.empty(dense.shape, np.float32)
        weights = np.empty(dense.shape, np.float32)
        run_rows(_dense_inputs, dense.shape[0], dense, values, weights)
        b = _local_mean(values, weights)
        h = int(round(sparse_interval / (2 * self.stride)))
        if h < 1 or 2 * h >= b.shape[1]:
            return np.zeros(b.shape, bool)
        out = np.empty(b.shape, np.bool_)
        run_rows(_bends, b.shape[0], dense, b, h, CURVED, out)
        return out


@nb.njit(cache=True, error_model="numpy", nogil=True, **NO_CFUNC)
def _dense_inputs(dense, values, weights, i0, i1):
    """``values``: the dense intervals in float32, 0 where not finite; ``weights``: 1 where
    they are positive, else 0 (grid rows ``i0 .. i1``)."""
    w = dense.shape[1]
    for i in range(i0, i1):
        for j in range(w):
            x = dense[i, j]
            finite = np.isfinite(x)
            values[i, j] = np.float32(x) if finite else np.float32(0.0)
            weights[i, j] = np.float32(1.0) if finite and x > 0.0 else np.float32(0.0)


@nb.njit(cache=True, error_model="numpy", nogil=True, **NO_CFUNC)
def _bends(dense, b, h, curved, out, i0, i1):
    """:meth:`IntervalModel._curved`'s test on grid rows ``i0 .. i1``: the mean of ``b``
    ``h`` cells either side against ``b`` (float32, as numpy computed it)."""
    w = b.shape[1]
    for i in range(i0, i1):
        for j in range(w):
            out[i, j] = False
            if j < h or j >= w - h:
                continue
            # both sides measured: across a gap (an object's edge) may be another surface,
            # whose intervals are no bend of this one
            left = dense[i, j - h]
            right = dense[i, j + h]
            if not (np.isfinite(left) and left > 0.0 and np.isfinite(right) and right > 0.0):
                continue
            side = np.float32(0.5) * (b[i, j - h] + b[i, j + h])
            out[i, j] = abs(side / b[i, j] - np.float32(1.0)) > curved


def _local_mean(values: np.ndarray, weights: np.ndarray,
                blurred_weights: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
    """Gaussian mean of ``values`` (0 where ``weights`` is 0) over :data:`SMOOTH_CELLS`
    (``blurred_weights``: the blur of ``weights``, when the caller has it)."""
    if blurred_weights is None:
        blurred_weights = cv2.GaussianBlur(weights, (0, 0), SMOOTH_CELLS)
    with np.errstate(invalid="ignore", divide="ignore"):
        return cv2.GaussianBlur(values, (0, 0), SMOOTH_CELLS) / blurred_weights


@nb.njit(cache=True, error_model="numpy", inline="always", **NO_CFUNC)
def _at(tab, p, k, f, r0, fr, c0, fc):
    """Table ``tab[p]`` at depth index ``k + f`` and coarse position ``(r0 + fr, c0 + fc)``."""
    acc = 0.0
    for dk in range(2):
        wk = f if dk else 1.0 - f
        for dr in range(2):
            wr = fr if dr else 1.0 - fr
            acc += wk * wr * ((1.0 - fc) * tab[p, k + dk, r0 + dr, c0]
                              + fc * tab[p, k + dk, r0 + dr, c0 + 1])  # fmt: skip
    return acc


@nb.njit(cache=True, error_model="numpy", inline="always", **NO_CFUNC)
def _other_du(pitch_d, b_d, a_d, c_d, a_s, c_s):
    """Pattern ``s``'s ``du/dx`` where pattern ``d``'s measured interval ``b_d`` fixes
    ``dz/dx`` (its ``du/dx`` taken with the sign it has at a fixed depth, ``a_d``)."""
    g = (math.copysign(pitch_d / b_d, a_d) - a_d) / c_d
    return a_s + g * c_s


@nb.njit(cache=True, error_model="numpy", nogil=True, **INTERNAL)
def _predict(a, c, pitch, b_dense, d, s, t, r0, fr, c0, fc):
    """The sparse pattern ``s``'s ``du/dx`` predicted from the dense ``d``'s interval
    ``b_dense`` at depth index ``t``; 0 where there is no prediction."""
    nz = a.shape[1]
    if not (0.0 <= t <= nz - 1):
        return 0.0
    k = min(int(t), nz - 2)
    f = t - k
    ad = _at(a, d, k, f, r0, fr, c0, fc)
    cd = _at(c, d, k, f, r0, fr, c0, fc)
    as_ = _at(a, s, k, f, r0, fr, c0, fc)
    cs = _at(c, s, k, f, r0, fr, c0, fc)
    if cd == 0.0 or ad == 0.0:
        return 0.0
    du_s = _other_du(pitch[d], b_dense, ad, cd, as_, cs)
    if du_s == 0.0 or (du_s > 0.0) != (as_ > 0.0):
        return 0.0  # the prediction folds the surface over: keep the measurement
    return du_s


@nb.njit(cache=True, error_model="numpy", nogil=True, **NO_CFUNC)
def _disagreement(intervals, depth, a, c, pitch, inv_z0, inv_z_step, coarse, denser, depth_tol,
                  tol, out, have, i0, i1):  # fmt: skip
    """``out[s]``: log(measured / predicted) interval of the sparse pattern ``s`` of each
    cell, ``have[s]`` 1 there (grid rows ``i0 .. i1``).

    Only where the prediction moves by less than ``tol`` (log) when the depth is off
    by ``depth_tol`` (relative) either way.
    """
    gw = depth.shape[1]
    for i in range(i0, i1):
        r0 = i // coarse
        fr = (i - r0 * coarse) / coarse
        for j in range(gw):
            z = depth[i, j]
            b0 = intervals[0, i, j]
            b1 = intervals[1, i, j]
            if not (z > 0.0 and b0 > 0.0 and b1 > 0.0):
                continue
            c0 = j // coarse
            fc = (j - c0 * coarse) / coarse
            # the dense pattern (the shorter interval) is the reference, if it samples the
            # surface at least DENSER times as finely: else it knows no more
            d = 0 if b0 <= b1 else 1
            s = 1 - d
            if intervals[s, i, j] < denser * intervals[d, i, j]:
                continue
            t = (1.0 / z - inv_z0) / inv_z_step
            du_s = _predict(a, c, pitch, intervals[d, i, j], d, s, t, r0, fr, c0, fc)
            if du_s == 0.0:
                continue
            # the depth comes from the flows, which the measured interval biases: where a
            # depth off by what a kept pixel may be off moves the prediction by more than
            # the tolerance, it knows no better than the measurement (and would hold the
            # depth where the bias put it)
            ok = True
            for sign in (-1.0, 1.0):
                tz = (1.0 / (z * (1.0 + sign * depth_tol)) - inv_z0) / inv_z_step
                du2 = _predict(a, c, pitch, intervals[d, i, j], d, s, tz, r0, fr, c0, fc)
                if du2 == 0.0 or abs(math.log(du2 / du_s)) > tol:
                    ok = False
            if not ok:
                continue
            out[s, i, j] = math.log(intervals[s, i, j] * abs(du_s) / pitch[s])
            have[s, i, j] = 1.0


def warm_up() -> None:
    """Compile (or load) :meth:`IntervalModel.depth`'s kernel with a frame's argument types.

    It runs only where lines move too little for a flow, so a test image of
    straight stripes never reaches it (a helper process may call this instead).
    """
    grids = np.full((2, 2, 4, 4), 20.0)  # the pipeline passes a field of its grids: a view
    z = np.empty((4, 4), np.float32)
    sens = np.empty((4, 4), np.float32)
    tab = np.ones((2, 2, 2, 2))
    _interval_depth(grids[:, 1], np.ones((4, 4), np.bool_), tab, tab, np.array([20.0, 40.0]),
                    1.0, 0.1, COARSE, z, sens, 0, 4)  # fmt: skip


#: largest ``|d log(B_1 / B_0) / d log z|`` of a depth the intervals give.  Rigs give
#: 0.4-1; where the dense pattern's ``du/dx`` (fixed by its interval, with the sign it has
#: at a fixed depth) passes through 0 over the depth range, the predicted interval has a
#: pole, and the residual jumps through 0 there (10-50): on tuning rigs 9 and 10 the only
#: sign change of boards at 0.61 m (whose residual there just touched 0) was such a pole
#: at 0.36 m
MAX_SENSITIVITY = 5.0
#: :meth:`IntervalModel.depth` looks for the depth on every SCAN-th depth of the
#: tables first, then between the two that bracket it (the residual is smooth in 1/z)
SCAN = 3


@nb.njit(cache=True, error_model="numpy", **INTERNAL)
def _interval_residual(a, c, pitch, b0, b1, k, r0, fr, c0, fc):
    """Pattern 1's interval predicted at depth index ``k`` over the measured one, minus 1.

    Pattern 0's interval fixes dz/dx (:func:`_other_du`).  No log: only its zero and
    the slope there are used, where the two agree.
    """
    nz = a.shape[1]
    kk = min(k, nz - 2)  # _at reads the next depth too (at weight 0 here)
    a0 = _at(a, 0, kk, k - kk, r0, fr, c0, fc)
    k0 = _at(c, 0, kk, k - kk, r0, fr, c0, fc)
    if k0 == 0.0:
        return np.nan
    a1 = _at(a, 1, kk, k - kk, r0, fr, c0, fc)
    k1 = _at(c, 1, kk, k - kk, r0, fr, c0, fc)
    return abs(_other_du(pitch[0], b0, a0, k0, a1, k1)) * b1 / pitch[1] - 1.0


@nb.njit(cache=True, error_model="numpy", nogil=True, **NO_CFUNC)
def _interval_depth(intervals, where, a, c, pitch, inv_z0, inv_z_step, coarse, z_out, sens_out,
                    i0, i1):  # fmt: skip
    """:meth:`IntervalModel.depth` on grid rows ``i0 .. i1``."""
    nz = a.shape[1]
    w = intervals.shape[2]
    ks = np.empty(nz, np.int64)  # the scanned depth indices, the last one included
    n = 0
    for k in range(0, nz, SCAN):
        ks[n] = k
        n += 1
    if ks[n - 1] != nz - 1:
        ks[n] = nz - 1
        n += 1
    res = np.empty(n)
    for i in range(i0, i1):
        fi = i / coarse
        r0 = int(fi)
        fr = fi - r0
        for j in range(w):
            z_out[i, j] = np.nan
            sens_out[i, j] = np.nan
            b0 = intervals[0, i, j]
            b1 = intervals[1, i, j]
            if not (where[i, j] and b0 > 0.0 and b1 > 0.0):
                continue
            fj = j / coarse
            c0 = int(fj)
            fc = fj - c0
            for q in range(n):
                res[q] = _interval_residual(a, c, pitch, b0, b1, ks[q], r0, fr, c0, fc)
            found = -1
            for q in range(n - 1):
                if np.isfinite(res[q]) and np.isfinite(res[q + 1]) \
                        and (res[q] <= 0.0) != (res[q + 1] <= 0.0):  # fmt: skip
                    # a pole jumps through 0 far more steeply than a root crosses it (at
                    # most MAX_SENSITIVITY over the bracket's span of log z): not a depth,
                    # and no second one beside a true root
                    span = math.log((inv_z0 + ks[q] * inv_z_step)
                                    / (inv_z0 + ks[q + 1] * inv_z_step))  # fmt: skip
                    if abs(res[q + 1] - res[q]) > MAX_SENSITIVITY * abs(span):
                        continue
                    if found >= 0:
                        found = -2  # two depths explain the intervals: none is known
                        break
                    found = q
            if found < 0:
                continue
            # the bracket's own depths, for the step that holds the zero
            lo = ks[found]
            r_lo = res[found]
            r_hi = res[found + 1]
            for k in range(ks[found] + 1, ks[found + 1]):
                r = _interval_residual(a, c, pitch, b0, b1, k, r0, fr, c0, fc)
                if not np.isfinite(r):
                    break
                if (r <= 0.0) != (r_lo <= 0.0):
                    r_hi = r
                    break
                lo = k
                r_lo = r
            # the tables are uniform in 1/z: log z changes by log(iz_k / iz_k+1) per step
            dlogz = math.log((inv_z0 + lo * inv_z_step) / (inv_z0 + (lo + 1) * inv_z_step))
            sens = abs((r_hi - r_lo) / dlogz)
            if sens > MAX_SENSITIVITY:
                continue  # a pole of the prediction (a fold), not a depth
            f = r_lo / (r_lo - r_hi)
            z_out[i, j] = 1.0 / (inv_z0 + (lo + f) * inv_z_step)
            sens_out[i, j] = sens
