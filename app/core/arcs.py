"""A band's line interval from the circular arc through its line and its two neighbours.

A flow is a sweep over the local line interval, ``L / B``, with ``B = P / |du/dx|``
the spacing the pattern's lines would have at the band itself (``u`` the projector
column lit at camera column ``x``).  The detector measures the mean spacing to the
two neighbouring lines, a whole interval away on either side: on a curved surface
that is the slope of a secant, not of the tangent.  Against the renderer's truth on
the evaluation matrix's balls it is 0.3-1.6 % long, and since the two patterns'
secants differ, the flow ratio carries the difference: -5 to -28 mm of depth.  With
the true tangent at every band the balls' median errors fall from 12-28 mm to 3-5 mm
(a test that replaced the intervals by the renderer's).

Three lines fix more than a secant when the geometry is used.  With a depth ``z0``
for the band (the first pass's, from the flows), the band's surface point is
``X0 = z0 r(c0)`` (``r`` the camera ray of its centre ``c0``).  Its neighbours lie
on their own rays, one pitch further along the projector's columns: each ray is
searched for the depth whose point the projector lights at ``u(X0) +- P`` (in closed
form for a pinhole projector, then Newton through its lens).  The surface's
cross-section through the three points is taken as the circle through them (a line
when they are in line): exact on spheres and planes, and second-order elsewhere,
like a parabola.  Its tangent at ``X0`` is ``|a|^2 c - |c|^2 a``, with ``a``, ``c``
the vectors from ``X0`` to the neighbours; the interval is the pitch over the
projector's column change per camera column along it (both through the lenses).

The depth is needed only to place the triangle: on the rendered balls a depth 2 %
off changes the intervals by less than 0.01 %.  A band gets its interval this way
where both neighbours are detected with spacings that agree (the detector's plain
interval, possibly with the whole-column snapping taken out, :mod:`.snapping`): its
interval is scaled by the arc's over the secant's.  Where snapping knows the run's
lines, the neighbours are taken where the lines would be at their nominal columns
(the whole-column steps, up to half a column, would bend the arc).  The arc must
change the interval by :data:`MIN_CHANGE` or more, the same way as a band beside,
above or below: on a plane the two differ only by noise, scattered, and every cell
that changes is read again (:meth:`.flow.FlowModel.reread`).

The outermost band of a run where the lines bunch towards a limb has no interval
from the detector (``BAND_LIMB``: a straight extrapolation comes out 4-13 % short
there).  The arc through it and its run's next two lines gives it one, and the band
becomes valid: on the evaluation matrix's balls this took coverage from 20-52 % to
36-61 %.  So does a band whose two spacings differ too much for their mean with no step
beside it (``BAND_STEEP``: the lines bend fast), with the arc through its neighbours if
that lies between its two spacings, as a tangent on one smooth surface does.  Such bands
have no depth of their own yet: the nearest cell's within :data:`DEPTH_REACH` serves.
Near a limb that can be far off, so where the depth the frame then measures at such a
band differs by more than :data:`RECHECK`, its arc is placed again there
(:meth:`ArcIntervals.recheck`; the pipeline reads the flows again).
Two projectors with uniform patterns only.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .bands import (
    BAND_LIMB,
    BAND_STEEP,
    BAND_VALID,
    F_CENTRE,
    F_INTERVAL,
    F_LENGTH,
    F_RAMP,
    F_VALID,
)
from .geometry import lens_coefficients, lens_distort, lens_distort_derivative, undistort_pixels
from .kernel_options import INTERNAL, NO_CFUNC
from .rig import Rig
from .snapping import column_direction
from .threads import run_rows

#: Newton steps for a neighbour's depth along its ray (converges in 2-4)
NEWTON_STEPS = 8
#: a neighbour's projector column must be met within this many projector pixels
NEWTON_TOLERANCE_PX = 1e-3
#: the arc's interval may differ from the secant's by at most this factor either way
#: (beyond it the three lines are not on one smooth surface, or a depth is wrong)
MAX_CHANGE = 1.25
#: an arc that changes the interval by less than this share leaves it alone, and so does
#: one that no band beside, above or below agrees with (by half as much, the same way):
#: on planes the two differ by the centres' noise (boards: a median of 0.003 %, 1 % of
#: the bands beyond 0.2 %, scattered), on balls by the surface's bend (98 % of the bands
#: beyond 0.2 %); each changed cell is read again
MIN_CHANGE = 0.002
#: a limb band's two spacings, and its arc interval and the spacing to the next line,
#: may differ by at most this factor (the lines bunch towards the limb, smoothly)
LIMB_CHANGE = 1.6
#: a steep band's arc interval must lie between its two spacings, give or take this factor
#: (on one smooth surface the tangent at a line lies between the secants on its sides)
STEEP_SLACK = 1.02
#: grid cells searched around a band (or a limb band's run) for a first-pass depth, in any
#: direction: 24 camera px at the default stride, under a line interval.  The arc hardly
#: depends on the depth (2 % off moves it by under 0.01 %), and a limb or steep band's
#: own cell has none (nor, often, a valid band's whose secant put its depth out of range)
DEPTH_REACH = 6
#: a limb or steep band that became valid is placed again (:meth:`ArcIntervals.recheck`)
#: where the depth its frame then measured at its own cell differs from the one its arc
#: was placed at by more than this share.  With no depth of their own, such bands take
#: the nearest cell's, and near a limb that is often a first-pass depth 10-40 % off (the
#: flows of other limb bands): an arc placed 40 % off reads about 10 % long, the flows
#: with it, and the triangulation then names the lines one off.  Tuning rigs: of the
#: bands whose depths differ by over 10 %, 90-100 % had been placed more than 10 % off,
#: and the frame's depth at their cells was within 0-5 % in the median; 0.05 against
#: 0.1 gained one case 2 points, 0.2 the same as 0.1.  The depth measured is the
#: smoothed one with the intervals' (a median of the flows' own around the band, or the
#: smoothed depth without the intervals', kept most of the first pass's errors)
RECHECK = 0.05
#: a steep band's arc and those through its line and the next two on either side must
#: agree within this share: one smooth surface.  Beside a depth edge they differ by far
#: more (the ball before a wall of tests/test_arcs.py), on a sphere by under 0.01 %
SIDES_AGREE = 0.01


class ArcIntervals:
    """Per-band line intervals from the arc through three lines (both patterns).

    Parameters
    ----------
    rig : Rig
        Two projectors with uniform patterns.
    row_y : numpy.ndarray
        The image rows the band detector measures (one per row of its output).
    depth : float
        A depth (m) in the working range, at which the direction of each projector's
        columns along the camera rows is found.
    """

    def __init__(self, rig: Rig, row_y: np.ndarray, depth: float = 1.0):
        cam = rig.camera
        cols = np.arange(cam.width, dtype=np.float64)
        pix = np.stack(np.broadcast_arrays(cols[None, :], np.asarray(row_y, np.float64)[:, None]),
                       axis=-1)  # fmt: skip
        #: normalised camera coordinates (x/z, y/z) of every column of the measured rows
        self.rays = np.ascontiguousarray(undistort_pixels(cam.K, cam.dist, pix))
        self.cam_k = np.asarray(cam.K, np.float64)
        self.cam_lens = lens_coefficients(cam.dist)
        self.rot = np.stack([np.asarray(proj.R, np.float64) for proj, _ in rig.patterns])
        self.shift = np.stack([np.asarray(proj.t, np.float64) for proj, _ in rig.patterns])
        self.k = np.stack([np.asarray(proj.K, np.float64) for proj, _ in rig.patterns])
        self.lens = np.stack([lens_coefficients(proj.dist) for proj, _ in rig.patterns])
        #: per projector, whether its lens distorts (else depths along rays in closed form)
        self.distorted = np.array([bool(np.any(np.asarray(proj.dist, float)))
                                   for proj, _ in rig.patterns])  # fmt: skip
        self.pitch = np.array([pat.pitch_px for _, pat in rig.patterns], np.float64)
        #: per projector, +1 where its columns grow along the camera rows, else -1
        self.direction = np.array([float(column_direction(cam, proj, depth))
                                   for proj, _ in rig.patterns])  # fmt: skip

    def recheck(self, before: np.ndarray, after: np.ndarray, counts: np.ndarray,
                depth: np.ndarray, measured: np.ndarray, rows_per_cell: int,
                stride: int) -> np.ndarray | None:  # fmt: skip
        """The depth to place the arcs at again, where limb and steep bands were placed off.

        A band that :meth:`correct` made valid was placed at the depth of the cell
        nearest to it (it had none of its own).  Where the frame's depth at the band's
        own cell (``measured``, read with the arcs' intervals) differs from that one by
        more than :data:`RECHECK`, the band's cell takes the measured depth, so that
        :meth:`correct` on ``before`` with the map returned places the band there.

        Parameters
        ----------
        before, after : numpy.ndarray
            Both patterns' bands before and after :meth:`correct` (``(2, rows, bands,
            fields)``).
        counts : numpy.ndarray
            ``(2, rows)`` band counts.
        depth : numpy.ndarray
            ``(h, w)`` the depth (m) :meth:`correct` was given.
        measured : numpy.ndarray
            ``(h, w)`` the depth (m) measured with the arcs' intervals; NaN where none.
        rows_per_cell, stride : int
            The analysis grid.

        Returns
        -------
        numpy.ndarray or None
            ``depth`` with the flagged bands' cells replaced (float64), or None when no
            band is flagged.
        """
        depth = np.ascontiguousarray(depth, dtype=np.float64)
        measured = np.ascontiguousarray(measured, dtype=np.float64)
        marks = np.full(depth.shape, np.nan)
        flagged = 0
        for p in range(2):
            flagged += _recheck(before[p], after[p], counts[p], depth, measured, rows_per_cell,
                                stride, RECHECK, marks)  # fmt: skip
        if not flagged:
            return None
        return np.where(np.isfinite(marks), marks, depth)

    def correct(self, bands: np.ndarray, counts: np.ndarray, nominal: np.ndarray, depth: np.ndarray,
                rows_per_cell: int, stride: int,
                interval_tolerance: float) -> tuple[int, int, np.ndarray]:  # fmt: skip
        """Scale each eligible band's ``F_INTERVAL`` by the arc's interval over the secant's,
        and give limb bands (``BAND_LIMB``) the arc's interval through their run's next two
        lines and steep bands (``BAND_STEEP``) the arc's through their neighbours, valid
        where it leaves their support a gap.

        Parameters
        ----------
        bands, counts : numpy.ndarray
            Both patterns' detector output ``(2, rows, bands, fields)`` and counts
            ``(2, rows)`` (changed in place).
        nominal : numpy.ndarray
            ``(2, rows, bands)``: each band's centre had its lines been at their
            nominal columns, where snapping knows them (:func:`.snapping.desnap_intervals`),
            else NaN.
        depth : numpy.ndarray
            ``(h, w)`` depth (m) on the analysis grid; NaN where none.
        rows_per_cell, stride : int
            Measured rows per grid row, and the grid's stride (camera px).
        interval_tolerance : float
            The detector's: spacings on the two sides of a band that differ by more
            than this share of their mean are not one smooth surface's.

        Returns
        -------
        (int, int, numpy.ndarray)
            Bands whose interval was scaled, limb and steep bands that became valid
            with their arc's, and the grid rows that hold either.
        """
        rows = bands.shape[1]
        changed = np.zeros(rows, np.int64)
        rescued = np.zeros(rows, np.int64)
        depth = np.ascontiguousarray(depth, dtype=np.float64)
        # each band's arc over its secant first, then those that agree with a neighbour's
        ratio = np.empty(bands.shape[1:3])
        for p in range(2):
            for second in (False, True):
                run_rows(_arc_rows, rows, bands[p], counts[p], nominal[p], self.rays, self.cam_k,
                         self.cam_lens, depth, rows_per_cell, stride, self.rot[p], self.shift[p],
                         self.k[p], self.lens[p], self.distorted[p], self.direction[p],
                         self.pitch[p], interval_tolerance, ratio, rescued, second)  # fmt: skip
            run_rows(_apply_rows, rows, bands[p], counts[p], ratio, changed)
        touched = np.flatnonzero((changed + rescued) > 0) // rows_per_cell
        return int(changed.sum()), int(rescued.sum()), np.unique(touched)


@nb.njit(cache=True, error_model="numpy", inline="always", **NO_CFUNC)
def _column(rot, shift, kmat, lens, px, py, pz):
    """Projector column lighting the camera-frame point ``(px, py, pz)``."""
    qx = rot[0, 0] * px + rot[0, 1] * py + rot[0, 2] * pz + shift[0]
    qy = rot[1, 0] * px + rot[1, 1] * py + rot[1, 2] * pz + shift[1]
    qz = rot[2, 0] * px + rot[2, 1] * py + rot[2, 2] * pz + shift[2]
    xd, yd = lens_distort(lens, qx / qz, qy / qz)
    return kmat[0, 0] * xd + kmat[0, 1] * yd + kmat[0, 2]


@nb.njit(cache=True, error_model="numpy", _nrt=False, **INTERNAL)
def _ray(rays, r, x):
    """Normalised ray (x/z, y/z) at fractional column ``x`` of measured row ``r``."""
    w = rays.shape[1]
    j = min(max(int(math.floor(x)), 0), w - 2)
    f = x - j
    return (rays[r, j, 0] + f * (rays[r, j + 1, 0] - rays[r, j, 0]),
            rays[r, j, 1] + f * (rays[r, j + 1, 1] - rays[r, j, 1]))  # fmt: skip


# The arcs' kernels allocate nothing: compiled without numba's reference counting
# (``_nrt=False``), whose atomic counts on the rig's and the bands' arrays at every call
# (both threads on the same arrays) took a third of their time
@nb.njit(cache=True, error_model="numpy", nogil=True, _nrt=False, **INTERNAL)
def _depth_on_ray(rot, shift, kmat, lens, distorted, rx, ry, target, z):
    """Depth along the ray ``(rx, ry, 1)`` whose point the projector lights at column
    ``target`` (near ``z``); NaN when there is none near."""
    # the projector-frame point moves along (ax, ay, az) per metre of depth
    ax = rot[0, 0] * rx + rot[0, 1] * ry + rot[0, 2]
    ay = rot[1, 0] * rx + rot[1, 1] * ry + rot[1, 2]
    az = rot[2, 0] * rx + rot[2, 1] * ry + rot[2, 2]
    # a pinhole projector's column is a ratio of linear functions of the depth: solved
    # in closed form, which is the answer without lens distortion and a close start with
    k = target - kmat[0, 2]
    den = k * az - kmat[0, 0] * ax - kmat[0, 1] * ay
    if den != 0.0:
        zc = (kmat[0, 0] * shift[0] + kmat[0, 1] * shift[1] - k * shift[2]) / den
        if 0.5 * z < zc < 2.0 * z:
            z = zc
            if not distorted:
                return z
    for _ in range(NEWTON_STEPS):
        qx = ax * z + shift[0]
        qy = ay * z + shift[1]
        qz = az * z + shift[2]
        if not qz > 0.0:
            return np.nan
        x = qx / qz
        y = qy / qz
        dx = (ax * qz - qx * az) / (qz * qz)
        dy = (ay * qz - qy * az) / (qz * qz)
        xd, yd, dxd, dyd = lens_distort_derivative(lens, x, y, dx, dy)
        err = kmat[0, 0] * xd + kmat[0, 1] * yd + kmat[0, 2] - target
        slope = kmat[0, 0] * dxd + kmat[0, 1] * dyd
        if abs(err) < NEWTON_TOLERANCE_PX:
            return z
        if slope == 0.0:
            return np.nan
        step = err / slope
        # a step past a fifth of the depth: no nearby solution
        step = max(min(step, 0.2 * z), -0.2 * z)
        z -= step
        if not z > 0.0:
            return np.nan
    return np.nan


@nb.njit(cache=True, error_model="numpy", nogil=True, _nrt=False, **INTERNAL)
def _arc_interval(rays, cam_k, cam_lens, r, c0, z0, c1, n1, c2, n2, rot, shift, kmat, lens,
                  distorted, sgn, pitch):  # fmt: skip
    """Interval at ``c0`` (depth ``z0``) from the arc through it and the lines at ``c1``,
    ``c2``, ``n1`` and ``n2`` lines away (signed, along the row); NaN when it fails.
    ``sgn``: +1 where the projector's columns grow along the camera row, else -1."""
    x0, y0 = _ray(rays, r, c0)
    ox, oy, oz = x0 * z0, y0 * z0, z0
    u0 = _column(rot, shift, kmat, lens, ox, oy, oz)
    x1, y1 = _ray(rays, r, c1)
    x2, y2 = _ray(rays, r, c2)
    z1 = _depth_on_ray(rot, shift, kmat, lens, distorted, x1, y1, u0 + n1 * sgn * pitch, z0)
    z2 = _depth_on_ray(rot, shift, kmat, lens, distorted, x2, y2, u0 + n2 * sgn * pitch, z0)
    if not (z1 > 0.0 and z2 > 0.0):
        return np.nan
    ax, ay, az = x1 * z1 - ox, y1 * z1 - oy, z1 - oz
    cx, cy, cz = x2 * z2 - ox, y2 * z2 - oy, z2 - oz
    a2 = ax * ax + ay * ay + az * az
    c2_ = cx * cx + cy * cy + cz * cz
    # the circle's tangent at the band (the chord's direction when the three are in line)
    tx = a2 * cx - c2_ * ax
    ty = a2 * cy - c2_ * ay
    tz = a2 * cz - c2_ * az
    # how fast the camera column moves along the tangent (through the camera's lens: the
    # three points lie on the curve its row sees, which the circle follows)
    _, _, dxd, dyd = lens_distort_derivative(cam_lens, x0, y0, (tx * oz - ox * tz) / (oz * oz),
                                             (ty * oz - oy * tz) / (oz * oz))  # fmt: skip
    dpx_dl = cam_k[0, 0] * dxd + cam_k[0, 1] * dyd
    if dpx_dl == 0.0:
        return np.nan
    # the projector column along the tangent: the lens model's derivative
    qx = rot[0, 0] * ox + rot[0, 1] * oy + rot[0, 2] * oz + shift[0]
    qy = rot[1, 0] * ox + rot[1, 1] * oy + rot[1, 2] * oz + shift[1]
    qz = rot[2, 0] * ox + rot[2, 1] * oy + rot[2, 2] * oz + shift[2]
    dqx = rot[0, 0] * tx + rot[0, 1] * ty + rot[0, 2] * tz
    dqy = rot[1, 0] * tx + rot[1, 1] * ty + rot[1, 2] * tz
    dqz = rot[2, 0] * tx + rot[2, 1] * ty + rot[2, 2] * tz
    _, _, dxd, dyd = lens_distort_derivative(lens, qx / qz, qy / qz,
                                             (dqx * qz - qx * dqz) / (qz * qz),
                                             (dqy * qz - qy * dqz) / (qz * qz))  # fmt: skip
    du = abs((kmat[0, 0] * dxd + kmat[0, 1] * dyd) / dpx_dl)
    return pitch / du if du > 0.0 else np.nan


@nb.njit(cache=True, error_model="numpy", _nrt=False, **INTERNAL)
def _depth_around(depth, i, ca, cb, off, stride, reach):
    """Depth of the cell nearest to grid row ``i``'s columns ``ca .. cb`` (camera px) that
    has one, within ``reach`` cells in any direction; of equals, the one nearest to
    ``ca`` (along the row first: a limb band's run).  NaN if none."""
    gh, gw = depth.shape
    ja = int(math.floor((ca - off) / stride + 0.5))
    jb = int(math.floor((cb - off) / stride + 0.5))
    lo = min(ja, jb)
    hi = max(ja, jb)
    if 0 <= ja < gw and depth[i, ja] > 0.0:
        # the cell at ca itself: at distance 0 and nearest to ca, the search's answer
        return depth[i, ja]
    best = reach * reach + 1
    best_a = 0
    z = np.nan
    for ii in range(max(0, i - reach), min(gh, i + reach + 1)):
        di = ii - i
        for jj in range(max(0, lo - reach), min(gw, hi + reach + 1)):
            if not depth[ii, jj] > 0.0:
                continue
            dj = lo - jj if jj < lo else (jj - hi if jj > hi else 0)
            d = di * di + dj * dj
            da = abs(jj - ja)
            if d < best or (d == best and da < best_a):
                best = d
                best_a = da
                z = depth[ii, jj]
    return z


@nb.njit(cache=True, error_model="numpy", _nrt=False, **NO_CFUNC)
def _recheck(before, after, counts, depth, measured, k, stride, tol, marks):
    """:meth:`ArcIntervals.recheck` for one pattern: ``measured`` into ``marks`` (in place)
    at the cells of the flagged bands; returns how many were flagged.  The depth each
    band was placed at is found on ``depth`` as :func:`_arc_rows` found it."""
    gh, gw = depth.shape
    off = 0.5 * (stride - 1)
    flagged = 0
    for r in range(before.shape[0]):
        i = r // k
        if i >= gh:
            continue
        n = counts[r]
        for b in range(n):
            code = before[r, b, F_VALID]
            if after[r, b, F_VALID] != BAND_VALID or not (code == BAND_LIMB
                                                         or code == BAND_STEEP):  # fmt: skip
                continue
            c0 = before[r, b, F_CENTRE]
            if code == BAND_LIMB:
                s = 1 if b + 1 < n and np.isfinite(before[r, b + 1, F_CENTRE]) else -1
                z0 = _depth_around(depth, i, c0, before[r, b + s, F_CENTRE], off, stride,
                                   DEPTH_REACH)  # fmt: skip
            else:
                z0 = _depth_around(depth, i, c0, c0, off, stride, DEPTH_REACH)
            j = int(math.floor((c0 - off) / stride + 0.5))
            if not (z0 > 0.0 and 0 <= j < gw):
                continue
            m = measured[i, j]
            if m > 0.0 and abs(m / z0 - 1.0) > tol:
                marks[i, j] = m
                flagged += 1
    return flagged


@nb.njit(cache=True, error_model="numpy", nogil=True, _nrt=False, **NO_CFUNC)
def _arc_rows(bands, counts, nominal, rays, cam_k, cam_lens, depth, k, stride, rot, shift, kmat,
              lens, distorted, sgn, pitch, itol, ratio, rescued, second, r0, r1):  # fmt: skip
    """Measured rows ``r0 .. r1`` of one pattern: each band's arc interval over its secant in
    ``ratio`` (NaN where none); limb bands get theirs, and their validity, at once.

    Two passes keep planes cheap: the first (``second`` false) reads every other row (and
    the limb bands), the second the rows between, where a band of the first above or below
    changes its interval by at least half of :data:`MIN_CHANGE` (where none does, the
    others would mostly not be applied either).
    """
    gh = depth.shape[0]
    off = 0.5 * (stride - 1)
    for r in range(r0, r1):
        n = counts[r]
        i = r // k
        if not second:
            for b in range(n):
                ratio[r, b] = np.nan
        if i >= gh:
            continue
        if second:
            # only the odd rows, and only beside a row of the first pass that changes: a
            # pass over each of those rows spares a search of it per band
            if r % 2 == 0:
                continue
            above = _row_changes(ratio, counts, r - 1)
            below = _row_changes(ratio, counts, r + 1)
            if not (above or below):
                continue
        for b in range(n):
            code = bands[r, b, F_VALID]
            c0 = bands[r, b, F_CENTRE]
            seed = r % 2 == 0
            steep = code == BAND_STEEP and not second
            if (steep or code == BAND_VALID and seed != second) and 0 < b < n - 1:
                # the rows between: only near a band of the first pass (the even rows, not
                # written now) above or below whose interval changes
                if second and not (
                        above and _changes_near(ratio, counts, bands, r - 1, c0,
                                                bands[r, b, F_INTERVAL], 0.0)
                        or below and _changes_near(ratio, counts, bands, r + 1, c0,
                                                   bands[r, b, F_INTERVAL], 0.0)):  # fmt: skip
                    continue
                cp = bands[r, b - 1, F_CENTRE]
                cn = bands[r, b + 1, F_CENTRE]
                d1 = c0 - cp
                d2 = cn - c0
                if not (d1 > 2.0 and d2 > 2.0):
                    continue
                plain = 0.5 * (d1 + d2)
                # one smooth surface: the detector's plain interval (or snapping's
                # correction of it), not one from a side of a depth edge or a trend; or a
                # steep band's, whose spacings differ too much for their mean (the lines
                # bend fast): the arc gives it an interval, and validity
                if not steep and (abs(d1 - d2) > itol * plain
                                  or abs(bands[r, b, F_INTERVAL] / plain - 1.0) > 0.1):  # fmt: skip
                    continue
                z0 = _depth_around(depth, i, c0, c0, off, stride, DEPTH_REACH)
                if not z0 > 0.0:
                    continue
                # where snapping knows the run's lines, the neighbours where they would be
                # at their nominal columns: the whole-column steps would bend the arc
                d1n = nominal[r, b] - nominal[r, b - 1]
                d2n = nominal[r, b + 1] - nominal[r, b]
                if d1n > 0.0 and d2n > 0.0:
                    d1, d2 = d1n, d2n
                arc = _arc_interval(rays, cam_k, cam_lens, r, c0, z0, c0 - d1, -1.0, c0 + d2, 1.0,
                                    rot, shift, kmat, lens, distorted, sgn, pitch)  # fmt: skip
                if steep:
                    between = min(d1, d2) / STEEP_SLACK < arc < max(d1, d2) * STEEP_SLACK
                    if between and _sides_agree(bands, n, r, b, arc, rays, cam_k, cam_lens, z0,
                                                rot, shift, kmat, lens, distorted, sgn, pitch):
                        _rescue(bands, r, b, arc, rescued)
                    continue
                secant = 0.5 * (d1 + d2)
                if secant / MAX_CHANGE < arc < secant * MAX_CHANGE:
                    ratio[r, b] = arc / secant
            elif code == BAND_LIMB and not second:
                # the outermost band of a run: its two neighbours on the run's side
                s = 1 if b + 1 < n and np.isfinite(bands[r, b + 1, F_CENTRE]) else -1
                if not (0 <= b + 2 * s < n):
                    continue
                c1 = bands[r, b + s, F_CENTRE]
                c2 = bands[r, b + 2 * s, F_CENTRE]
                d1 = abs(c1 - c0)
                d2 = abs(c2 - c1)
                # spacings that jump rather than bunch: not a smooth limb (a grazing
                # surface, or another object's lines)
                if not (d1 > 2.0 and d2 > 2.0 and max(d1, d2) < LIMB_CHANGE * min(d1, d2)):
                    continue
                z0 = _depth_around(depth, i, c0, c1, off, stride, DEPTH_REACH)
                if not z0 > 0.0:
                    continue
                arc = _arc_interval(rays, cam_k, cam_lens, r, c0, z0, c1, float(s), c2, 2.0 * s,
                                    rot, shift, kmat, lens, distorted, sgn, pitch)  # fmt: skip
                if d1 / LIMB_CHANGE < arc < d1 * LIMB_CHANGE:
                    _rescue(bands, r, b, arc, rescued)


@nb.njit(cache=True, error_model="numpy", _nrt=False, **INTERNAL)
def _sides_agree(bands, n, r, b, arc, rays, cam_k, cam_lens, z0, rot, shift, kmat, lens,
                 distorted, sgn, pitch):  # fmt: skip
    """Whether the arcs through band ``b``'s line and its next two on either side both
    agree with ``arc`` (through a neighbour on each side) within :data:`SIDES_AGREE`: one
    smooth surface, not a depth edge beside the band."""
    c0 = bands[r, b, F_CENTRE]
    for s in (-1, 1):
        if not (0 <= b + 2 * s < n):
            return False
        c1 = bands[r, b + s, F_CENTRE]
        c2 = bands[r, b + 2 * s, F_CENTRE]
        if not (abs(c2 - c1) > 2.0):
            return False
        side = _arc_interval(rays, cam_k, cam_lens, r, c0, z0, c1, float(s), c2, 2.0 * s,
                             rot, shift, kmat, lens, distorted, sgn, pitch)  # fmt: skip
        if not abs(side / arc - 1.0) < SIDES_AGREE:
            return False
    return True


@nb.njit(cache=True, error_model="numpy", _nrt=False, **INTERNAL)
def _rescue(bands, r, b, arc, rescued):
    """Band ``b`` of measured row ``r`` (limb or steep) becomes valid with the interval
    ``arc`` where its support leaves a gap (as the detector's test, whose interval was
    the straight extrapolation or the mean)."""
    support = bands[r, b, F_LENGTH] + 2.0 * bands[r, b, F_RAMP] / 0.6
    if support <= arc:
        bands[r, b, F_INTERVAL] = arc
        bands[r, b, F_VALID] = BAND_VALID
        rescued[r] += 1


@nb.njit(cache=True, error_model="numpy", _nrt=False, **INTERNAL)
def _row_changes(ratio, counts, r):
    """Whether a band of row ``r`` has its interval changed by at least half of
    :data:`MIN_CHANGE` (:func:`_changes_near` finds one near a column only then)."""
    if r < 0 or r >= counts.shape[0]:
        return False
    for q in range(counts[r]):
        if abs(ratio[r, q] - 1.0) >= 0.5 * MIN_CHANGE:
            return True
    return False


@nb.njit(cache=True, error_model="numpy", _nrt=False, **INTERNAL)
def _changes_near(ratio, counts, bands, r, c, reach, dev):
    """Whether a band of row ``r`` within ``reach`` of column ``c`` has its interval changed
    by at least half of :data:`MIN_CHANGE`, the same way as ``dev`` (either way when ``dev``
    is 0).  Only centres and ratios are read there: another thread may be scaling that
    row's intervals."""
    if r < 0 or r >= counts.shape[0]:
        return False
    for q in range(counts[r]):
        d = ratio[r, q] - 1.0
        if abs(bands[r, q, F_CENTRE] - c) < reach and abs(d) >= 0.5 * MIN_CHANGE \
                and (dev == 0.0 or d * dev > 0.0):  # fmt: skip
            return True
    return False


@nb.njit(cache=True, error_model="numpy", nogil=True, _nrt=False, **NO_CFUNC)
def _apply_rows(bands, counts, ratio, changed, r0, r1):
    """Measured rows ``r0 .. r1``: scale the intervals whose arc changes them by at least
    :data:`MIN_CHANGE` where a band beside, above or below changes the same way."""
    for r in range(r0, r1):
        for b in range(counts[r]):
            dev = ratio[r, b] - 1.0
            if not abs(dev) >= MIN_CHANGE:
                continue
            c = bands[r, b, F_CENTRE]
            reach = 0.5 * bands[r, b, F_INTERVAL]
            near = ((b > 0 and (ratio[r, b - 1] - 1.0) * dev > 0.0
                     and abs(ratio[r, b - 1] - 1.0) >= 0.5 * MIN_CHANGE)
                    or (b + 1 < counts[r] and (ratio[r, b + 1] - 1.0) * dev > 0.0
                        and abs(ratio[r, b + 1] - 1.0) >= 0.5 * MIN_CHANGE)
                    or _changes_near(ratio, counts, bands, r - 1, c, reach, dev)
                    or _changes_near(ratio, counts, bands, r + 1, c, reach, dev))  # fmt: skip
            if near:
                bands[r, b, F_INTERVAL] *= ratio[r, b]
                changed[r] += 1


def warm_up() -> None:
    """Compile (or load from numba's cache) the arcs' kernels on two bands of an example
    rig's row (the rasterising of the grid rows they change:
    :func:`lightflow.app.core.pipeline.warm_up_kernels`).

    The demo's helper process runs this while the main one compiles the rest of the
    pipeline (about 3.5 s of CPU on a cold start).
    """
    from .bands import N_FIELDS
    from .rig import resolve_rig

    rig = resolve_rig("two-projector")
    arcs = ArcIntervals(rig, np.array([600]), 1.0)
    bands = np.full((2, 1, 8, N_FIELDS), np.nan)
    for p in range(2):
        centres = 700.0 + 40.0 * np.arange(5)
        bands[p, 0, :5, F_CENTRE] = centres
        bands[p, 0, :5, F_VALID] = BAND_VALID
        bands[p, 0, 0, F_VALID] = BAND_LIMB
        bands[p, 0, :5, F_INTERVAL] = 40.0
        bands[p, 0, :5, F_LENGTH] = 6.0
        bands[p, 0, :5, F_RAMP] = 1.0
    counts = np.full((2, 1), 5, np.int64)
    arcs.correct(bands, counts, np.full((2, 1, 8), np.nan), np.full((1, 400), 0.8), 1, 4, 0.25)
