"""Depth by triangulating each band's line, the line found where both patterns agree.

A band's centre is where its line lit the surface at mid-exposure (a line swept at a
steady speed is centred on its middle position).  Which line of the pattern it is
is not known from the image, but the flow's depth is near enough to name a few
candidates: the lines the projector shows around the column that depth predicts.
Each candidate gives a depth on the band's camera ray (the ray meets the projector's
plane of that line).  Candidates of one pattern differ by a whole line, 2-7 cm of
depth on the evaluation rigs, and so do those of the other pattern, by a different
amount.  So along a camera row, the runs of bands of the two patterns (consecutive
lines of one surface) are given one line offset each, the pair of offsets whose
depths agree with each other (within :data:`AGREE` of the depth) and clearly better
than any other pair; where two pairs agree (the patterns' depths per line near 1:2),
the one near the flow's depth, if the other is clearly farther.  The depth of such a
band is then the triangulated one, precise to about a tenth of a millimetre where the
flow's was precise to a centimetre, and it needs no line interval: bands near a
ball's limb or cut by an edge, rejected for the flow, still have a centre.

A run without a depth of its own takes the lines of the rows above or below (the same
line continues from row to row), a decided run is carried on past its ends band by
band where the other pattern's depth agrees (a ball's limb has no flow), and a band
still undecided takes the line of its line's trace where the trace is decided in the
rows above and below it.  Cells get depth from the triangulated bands along their row,
interpolated between two neighbouring bands of one surface, and only where the surface
moves: the cells a flow covers or whose lines are swept, and those between bands linked
to them through bands of one surface whose lines were not seen standing still.  A
static wall keeps no depth.
"""

from __future__ import annotations

import functools
import math

import cv2
import numba as nb
import numpy as np

from .bands import BAND_CUT, BAND_IRREGULAR, F_CENTRE, F_END, F_START, F_VALID
from .depth_model import DepthRange, proj_u_du, projector_params
from .geometry import LENS_COEFFICIENTS, undistort_pixels
from .kernel_options import INTERNAL, NO_CFUNC
from .medians import median_in_place
from .overlap import line_centred
from .patterns import line_columns
from .rig import Rig
from .snapping import column_direction
from .threads import run_rows, run_tasks

#: two patterns' triangulated depths of one surface agree within this share of the depth
#: (a band centre is precise to a few hundredths of a pixel: about 0.1 mm at 0.75 m on
#: the evaluation rigs; one line off moves a depth by 2-7 cm, 3-9 % of it)
AGREE = 0.004
#: a pair of line offsets is taken only when the next best pair disagrees by more than this
#: many times as much, plus :data:`RUNNER_UP`
MARGIN = 3.0
#: ... plus this share of the depth (tuning rigs: 0.003 -> 0.001 took the fans' p90 from
#: 23-40 to 14-34 mm and the balls' from 3-8 to 2-6 mm, nothing worse)
RUNNER_UP = 0.001
#: where two pairs of offsets agree (the patterns' depths per line near 1:2), the one
#: whose depths lie within this share of the priors (the flows' depths) is taken if the
#: other lies at least :data:`PRIOR_GAP` farther
PRIOR_REACH = 0.04
PRIOR_GAP = 0.04
#: where neither rule decides, a pair is still taken when it both agrees best, within
#: :data:`BOTH_AGREE` of the depth and :data:`BOTH_MARGIN` times better than the next
#: pair, and is the nearer to the priors by :data:`BOTH_GAP` (tuning rigs: the fans' p90
#: 9-19 -> 1-16 mm, the balls' +0-1 points of coverage; development rigs 40-42: 8 balls'
#: p90 down by 0.1-14 mm.  Without BOTH_AGREE, a ball whose bands' centres were
#: biased took a wrong pair agreeing at 0.37 %, where right ones agree at 0.03-0.08 %)
BOTH_AGREE = 0.0015
BOTH_MARGIN = 2.0
BOTH_GAP = 0.01
#: candidate line offsets on each side of the one the prior depth names
SEARCH = 2
#: neighbouring spacings of one run differ by less than this factor (else a new run)
RUN_RATIO = 1.6
#: a cell lies between two triangulated bands at most this many of their spacings apart,
#: and their depths differ by at most :data:`STEP` of the depth (else a depth edge)
GAP = 1.25
STEP = 0.05
#: a cell beyond the last triangulated band of its row keeps its depth this share of the
#: band's spacing out
REACH = 0.5
#: predicted error of a triangulated depth, as a share of it, before the two patterns'
#: disagreement is added (tuning rigs: the triangulated cells' errors are 0.1-0.2 mm in the
#: median at 0.6-0.9 m)
FLOOR = 0.0003
#: a band of the row above or below is the same line within this share of its spacing
LINK = 0.25
#: a band off the moving cells is on their surface when a chain of at most this many bands
#: of one surface links it to a band among them: a bound on a frame's work, not a rule
#: (tuning rigs: 40 and 1000 gave the same; 8, the twenty-first session's, cost the balls
#: 3-10 points of coverage once lines that moved between frames stopped no chain, and the
#: off-object depth stayed within 0.5 %)
HOPS = 64
#: the moving cells that start such chains are those with at least half the cells of this
#: window around them moving (a wall's lone cells whose noise passed as a sweep start
#: none: off-object depth on the balls before a wall 1.2-1.9 -> 0.3 %)
SEED_WINDOW = 5
#: and no chain enters a still cell, nor a cell with at least half of this window around
#: it still (a fan's hub, whose lines stand still but some of whose cells are not found
#: so: off-object depth on the fans 1.4 -> 1.0 and 2.2 -> 1.8 %)
STILL_WINDOW = 9
#: ... and a cell off the moving cells takes a band's depth beyond it only on the band's own
#: light (within this many camera px of its half-height edges), where its line lit the
#: surface: half a spacing beyond a ball's limb or a blade's edge is often the wall
#: (tuning rigs: off-object depth on the fans 1.0-1.8 -> 0.3-0.7 %, on the boards before
#: a wall 1.1 -> 0.0 %, for 2-11 points of the balls' coverage)
EXTENT = 1.0
#: a decided run is carried on band by band (:func:`_extend_rows`) where the depth on its
#: next line agrees within this share with the other pattern's decided bands around it
#: (tuning rigs, against the parabola through three of them, before the circle of
#: :func:`_other_depth`: 0.3 -> 0.5 % gained the
#: balls 1-2 points of coverage, and took a fan's off-object depth from 0.8 to 2.7 %: a
#: blade's next line met by a wall band by chance)
EXTEND_AGREE = 0.003
#: ... by at most this many bands on each side, twice: before the gaps in the lines'
#: traces are filled (:func:`_fill_traces`) and after (the second time also in rows the
#: fill did not change: a run stopped by this bound goes on; measured with the fill)
EXTEND_STEPS = 6
#: an undecided band takes the line of its line's trace (:func:`_fill_traces`) where the
#: trace's nearest decided bands above and below, at most this many image rows away,
#: both have that line ...
TRACE_REACH_PX = 128.0
#: ... and its depth on that line lies within this share of theirs, interpolated to its row
#: (tuning rigs: balls +2 to +11 points of coverage, fans +0 to +2, the fans' depth off
#: the blades +0.0-0.25 points; 1 % or 4 % and a reach of 64 or 256 px within a point or
#: two.  Traces that crossed cells near still lines took a fan's hub too, +0.3-0.9
#: points off the blades on development fans 43-48.  A band carried on from one row
#: alone, without the other end, took the balls +3 to +9 points further but a fan's blade
#: lines into its blurred edge, 2 -> 4-5 % of its depth off the blades.  Irregular bands
#: are filled too: left out, the balls lost 1-5 points and the fans' depth off the blades
#: stayed the same)
TRACE_AGREE = 0.02
#: the other pattern's depth (:func:`_other_depth`) is carried on past its decided bands
#: for one of their spacings, or for up to this many where their spacings change by at
#: least :data:`LIMB_CHANGE` towards the band (a limb, where one pattern's bands fade
#: before the other's; a plane's spacings change slowly), and there it must agree within
#: :data:`FAR_AGREE` of :data:`EXTEND_AGREE` (tuning rigs: balls +1 to +6 points of
#: coverage, fans' depth off the blades +0.0-0.06 points.  Without the spacing change,
#: development fan 47's blade lines went on over its hub: 3.4 -> 4.6 % off the blades;
#: the full agreement gained the balls 0-2 points more for up to 0.15 points off the fans)
FAR_REACH = 2.0
LIMB_CHANGE = 0.1
FAR_AGREE = 0.5
#: a cell beyond a ball's last triangulated band, towards its limb, takes the depth of the
#: circle through that band and the next two of its run (:func:`_limb_depth`) where their
#: spacings change by :data:`LIMB_CHANGE` or more and the circle ends (its rays miss it)
#: within this many of the band's spacings: the limb is where the circle ends, not half a
#: spacing past the band ...
LIMB_CLOSE = 1.5
#: ... for at most one of its spacings, and half-way at most to the next band without a
#: line (the wall behind a blade's edge).  Tuning rigs: the balls +1 to +7 points of
#: coverage (one projector's two balls +7), 0.0-0.05 % of their depth off them; fans and
#: boards unchanged but for the distorted rig's fan (+0.17 points off the blades, onto its
#: hub in the first frame).  Without that half-way bound the development fans took
#: +0.0-0.3 points off the blades; with a cut band among the three, the boards before a
#: wall +0.4 (a cut band's centre bends the circle)
LIMB_REACH = 1.0
#: a band without a line between two triangulated bands splits their surface where, at the
#: depth between them, its projector column lies further than this from a line (in lines;
#: :func:`_split_pairs`).  Development fans 43-48: 0.0-0.45 points less of their
#: depth off the blades (the wall between two blades at one depth), 0.0-0.2 points less
#: coverage (0.15, tried together with a change since dropped: within 0.15 points of 0.25)
SPLIT = 0.25
#: Newton iterations for the depth at which a ray meets a line's plane
NEWTON = 8


class LineTriangulation:
    """Triangulated depth for the bands of a rig's two patterns.

    Parameters
    ----------
    rig : Rig
        The rig (camera, projectors, patterns: the columns each line lights).
    row_y : numpy.ndarray
        The image row of each measured row of the band detector.
    depth_range : DepthRange
        Depths outside it are none.
    """

    def __init__(self, rig: Rig, row_y: np.ndarray, depth_range: DepthRange):
        cam = rig.camera
        self.projs = projector_params(rig)
        owner = {id(p): i for i, p in enumerate(rig.projectors)}
        pats = rig.patterns
        n_lines = max(len(line_columns(pat, proj.width)) for proj, pat in pats)
        self.lit = np.full((2, n_lines), np.nan)
        self.n_lit = np.zeros(2, np.int64)
        self.proj_of = np.zeros(2, np.int64)
        self.direction = np.zeros(2, np.int64)
        mid = 0.5 * (depth_range.near + depth_range.far)
        for p, (proj, pat) in enumerate(pats):
            cols = line_columns(pat, proj.width)
            # a line lights whole columns: its centre is theirs (those the projector has;
            # lines beyond it keep their own, which no band can show)
            lo, hi = cols[:, 0].astype(np.float64), cols[:, 1].astype(np.float64)
            inside = (hi >= 0) & (lo <= proj.width - 1)
            lo[inside] = np.maximum(lo[inside], 0.0)
            hi[inside] = np.minimum(hi[inside], proj.width - 1.0)
            centre = 0.5 * (lo + hi)
            self.lit[p, : len(cols)] = centre
            self.n_lit[p] = len(cols)
            self.proj_of[p] = owner[id(proj)]
            self.direction[p] = column_direction(cam, proj, mid)
        # the camera ray of every whole column of every measured row (sub-pixel centres
        # are interpolated: the lens model is smooth on that scale)
        cols = np.arange(cam.width, dtype=np.float64)
        ys = np.asarray(row_y, np.float64)
        pix = np.stack(np.broadcast_arrays(cols[None, :], ys[:, None]), axis=-1)
        self.rays = np.ascontiguousarray(undistort_pixels(cam.K, cam.dist, pix))
        self.near = float(depth_range.near)
        self.far = float(depth_range.far)
        self.row_y = ys

    def refine(self, bands, counts, rows_per_cell, stride, prior, moving, depth_grid,
               std_grid, still=None) -> int:  # fmt: skip
        """Triangulate the bands and write their depth into the grids (in place).

        Parameters
        ----------
        bands, counts : numpy.ndarray
            Both patterns' detector output (``(2, rows, max_bands, N_FIELDS)``).
        rows_per_cell, stride : int
            The analysis grid: ``rows_per_cell`` measured rows per grid row.
        prior : numpy.ndarray
            ``(gh, gw)`` depth (m) that names the candidate lines (the flow's): NaN
            where none.
        moving : numpy.ndarray
            ``(gh, gw)`` bool: the cells on a moving surface (they may get a depth).
        depth_grid, std_grid : numpy.ndarray
            ``(gh, gw)`` depth and its predicted error (m), overwritten where a cell
            has triangulated bands on both sides (or one, near).
        still : numpy.ndarray, optional
            ``(gh, gw)`` bool: the cells whose lines were measured standing still.  A
            triangulated band outside ``moving`` is on the moving surface when a chain
            of bands of one surface (:func:`_moving_bands`) links it to a band inside,
            through no still cell; the cells between such bands get a depth too.

        Returns
        -------
        int
            The number of cells written.
        """
        # a pulse of overlapping bands may lie between two lines: on one of them
        bands = line_centred(bands, counts)
        n_rows = counts.shape[1]
        line = np.full((2, n_rows, bands.shape[2]), -1, np.int64)
        z = np.full((2, n_rows, bands.shape[2]), np.nan)
        resid = np.full((2, n_rows, bands.shape[2]), np.nan)
        prior = np.ascontiguousarray(prior, np.float64)
        moving = np.ascontiguousarray(moving)
        args = (bands, counts, self.rays, self.projs, self.proj_of, self.lit, self.n_lit,
                self.direction, prior, rows_per_cell, stride, self.near, self.far, line, z,
                resid)  # fmt: skip
        # the flows' depths name the lines (rows on a thread per core: the kernel
        # releases the GIL), then the lines decided in the row above, and below
        run_rows(_decide_rows, n_rows, *args, 0, 1)
        _decide_rows(*args, 1, 1, 0, n_rows)
        _decide_rows(*args, 1, -1, 0, n_rows)
        # the runs carried on past their ends (rows on a thread per core)
        extend = (_extend_rows, n_rows, bands, counts, self.rays, self.projs, self.proj_of,
                  self.lit, self.n_lit, self.direction, self.near, self.far, line, z, resid)
        run_rows(*extend)
        # the gaps in a line's trace from row to row filled (the ends above and below on a
        # thread each), and the runs carried on again from the bands filled
        if still is None:
            still = np.zeros(moving.shape, np.bool_)
        seeds = moving & (_share(moving, SEED_WINDOW) >= 0.5)
        still_share = _share(still, STILL_WINDOW)
        barrier = still | (still_share >= 0.5)
        shape = (2, 2, n_rows, bands.shape[2])
        ends = (np.empty(shape, np.int64), np.empty(shape), np.empty(shape))
        # (no trace crosses a cell near lines seen standing still: a fan's hub, at the
        # blades' depth, and the wall behind a blade's blurred edge)
        near_still = still_share > 0.0
        run_tasks(*(functools.partial(_trace_ends, bands, counts, self.row_y, line, z, side,
                                      *ends, near_still, rows_per_cell, stride)
                    for side in range(2)))  # fmt: skip
        _fill_traces(bands, counts, self.rays, self.row_y, self.projs, self.proj_of, self.lit,
                     self.near, self.far, line, z, resid, *ends)
        run_rows(*extend)
        on_moving = _moving_bands(bands, counts, line, z, rows_per_cell, stride, seeds,
                                  barrier, HOPS)  # fmt: skip
        return _cells(bands, counts, line, z, resid, rows_per_cell, stride, moving, on_moving,
                      barrier, self.rays, self.projs, self.proj_of, self.lit, self.n_lit,
                      depth_grid, std_grid)  # fmt: skip


@nb.njit(cache=True, error_model="numpy", **INTERNAL)
def _column(pp, rx, ry, z):
    """:func:`~.depth_model.proj_u_du` compiled once for this module's kernels."""
    return proj_u_du(pp, rx, ry, z)


@nb.njit(cache=True, error_model="numpy", inline="always", **INTERNAL)
def _inverse_depth_step(z, u, du, column):
    """One Newton step towards the depth where projector column ``u`` (slope ``du``
    in depth, both at depth ``z``) becomes ``column``, taken in inverse depth (where
    the column is nearly linear): the new inverse depth (0 or less: none)."""
    return 1.0 / z + (column - u) / (-du * z * z)  # du/dw = du/dz * dz/dw = -du * z^2


@nb.njit(cache=True, error_model="numpy", **INTERNAL)
def _depth_on_line(pp, rx, ry, column, z0, near, far):
    """Depth at which the camera ray ``(rx, ry, 1)`` meets the projector's plane of
    ``column``, by Newton's method in inverse depth from ``z0``; NaN outside
    ``near .. far``."""
    z = z0
    for _ in range(NEWTON):
        u, du, pz = _column(pp, rx, ry, z)
        if not pz > 0.0 or du == 0.0:
            return np.nan
        w = _inverse_depth_step(z, u, du, column)
        if not w > 0.0:
            return np.nan
        z = 1.0 / w
        if abs(u - column) < 1e-4:
            break
    if not (near <= z <= far):
        return np.nan
    return z


@nb.njit(cache=True, error_model="numpy", **INTERNAL)
def _line_coordinate(lit, n, u):
    """Continuous line index of projector column ``u`` (lines in column order); NaN
    outside the pattern."""
    if not (u >= lit[0] and u <= lit[n - 1]):
        return np.nan
    lo = 0
    hi = n - 1
    while hi - lo > 1:
        m = (lo + hi) // 2
        if lit[m] <= u:
            lo = m
        else:
            hi = m
    return lo + (u - lit[lo]) / (lit[hi] - lit[lo])


#: no candidate offset for a run (no prior near it)
NONE = -(1 << 40)
#: bands of each run whose depths the search for a pair of offsets compares
SAMPLES = 6


@nb.njit(cache=True, error_model="numpy", nogil=True, **NO_CFUNC)
def _decide_rows(bands, counts, rays, projs, proj_of, lit, n_lit, direction, prior, k_rows,
                 stride, near, far, line, z, resid, vertical, order, r0, r1):  # fmt: skip
    """Decide the lines of the bands of every measured row (see :class:`LineTriangulation`).

    ``vertical`` 0: the priors are the flows' depths; 1: also the lines decided in the
    row before (``order`` +1: above, -1: below), for rows with bands still undecided.
    Measured rows ``r0 .. r1`` only (the first pass's rows are independent).  The
    search compares candidate depths from each band's projector column linearised in
    inverse depth at its prior, then once more at the candidate: two Newton steps (after
    the first, the candidates a line or two away were a few tenths of a per cent off, as
    much as :data:`AGREE`; with the second, on the tuning rigs, the fans' p90 fell from
    0.7-16 to 0.2-3.6 mm and the distorted rig's two balls' from 84 and 11 to 32 and 8
    mm, for 0.1-1.1 % more of the fans' depth off the blades).  The depths of the pair
    taken are then solved exactly.
    """
    n_rows = counts.shape[1]
    mb = bands.shape[2]
    gh, gw = prior.shape
    width = rays.shape[1]
    nc = 2 * SEARCH + 1
    off = 0.5 * (stride - 1)
    xs = np.empty((2, mb))
    slot = np.empty((2, mb), np.int64)
    rxy = np.empty((2, mb, 2))
    ell = np.empty((2, mb))
    zp = np.empty((2, mb))
    n_bands = np.zeros(2, np.int64)
    n_runs = np.zeros(2, np.int64)
    run_a = np.empty((2, mb), np.int64)
    run_b = np.empty((2, mb), np.int64)
    run_k = np.empty((2, mb), np.int64)
    run_fixed = np.empty((2, mb), np.int64)
    best_err = np.empty((2, mb))
    cand = np.empty((2, mb, nc))
    exact = np.empty((2, mb))
    tmp = np.empty(2 * SAMPLES)
    tmp2 = np.empty(2 * SAMPLES)
    # the bands a pair of runs compares (:func:`_samples`)
    s_t = np.empty(2 * SAMPLES, np.int64)
    s_u = np.empty(2 * SAMPLES, np.int64)
    s_f = np.empty(2 * SAMPLES)
    prio = np.empty(mb)
    fresh = np.empty((2, mb), np.bool_)
    # the projector column and its slope at a band's flow prior, computed once
    col_u = np.empty((2, mb))
    col_du = np.empty((2, mb))
    col_known = np.zeros((2, mb), np.bool_)
    # a band's prior where it names its line (NaN: none)
    z_named = np.empty(mb)
    for step in range(r1 - r0):
        r = r0 + step if order > 0 else r1 - 1 - step
        i = min(r // k_rows, gh - 1)
        o = r - order
        if vertical and not _linkable(bands, counts, line, r, o):
            continue
        for p in range(2):
            pp = projs[proj_of[p]]
            n = 0
            link_at = 0
            for q in range(counts[p, r]):
                x = bands[p, r, q, F_CENTRE]
                if not (np.isfinite(x) and 0.0 <= x <= width - 1):
                    continue
                xs[p, n] = x
                slot[p, n] = q
                c0 = min(int(x), width - 2)
                t = x - c0
                rx = rays[r, c0, 0] + t * (rays[r, c0 + 1, 0] - rays[r, c0, 0])
                ry = rays[r, c0, 1] + t * (rays[r, c0 + 1, 1] - rays[r, c0, 1])
                rxy[p, n, 0] = rx
                rxy[p, n, 1] = ry
                ell[p, n] = np.nan
                zp[p, n] = np.nan
                col_known[p, n] = False
                fresh[p, n] = not vertical
                z_named[n] = np.nan
                if vertical and line[p, r, q] >= 0:
                    ell[p, n] = line[p, r, q]
                    zp[p, n] = z[p, r, q]
                else:
                    j = _cell_column(x, off, stride, gw)
                    zf = prior[i, j]
                    if np.isfinite(zf) and near <= zf <= far:
                        z_named[n] = zf
                n += 1
            n_bands[p] = n
            # the projector columns at the priors, then their lines, each in a loop of its
            # own: the bands' columns are independent, and a loop of nothing else lets
            # the processor overlap them (interleaved with the searches' and the first
            # loop's unpredictable branches, each waited for its long chain of divisions)
            for t in range(n):
                if np.isfinite(z_named[t]):
                    u, du, pz = _column(pp, rxy[p, t, 0], rxy[p, t, 1], z_named[t])
                    if pz > 0.0:
                        zp[p, t] = z_named[t]
                        # kept: the candidates are linearised at this prior
                        col_u[p, t] = u
                        col_du[p, t] = du
                        col_known[p, t] = True
            for t in range(n):
                if col_known[p, t]:
                    ell[p, t] = _line_coordinate(lit[p], n_lit[p], col_u[p, t])
            if vertical and 0 <= o < n_rows:
                for t in range(n):
                    if line[p, r, slot[p, t]] < 0 and not np.isfinite(ell[p, t]):
                        # the same line in the row before: its decided index
                        q2, link_at = _same_line(bands, counts, line, p, o, xs[p, t], link_at)
                        if q2 >= 0:
                            ell[p, t] = line[p, o, q2]
                            zp[p, t] = z[p, o, q2]
                            fresh[p, t] = True
        for sweep in range(2):
            for p in range(2):
                pp = projs[proj_of[p]]
                n = n_bands[p]
                # runs: consecutive slots whose spacings change slowly (on the second
                # sweep, also split where the bands' lines were decided or not, or differ:
                # a run that crossed a depth step got its lines on one side only, and the
                # other side is a run of its own, to be paired anew)
                m = 0
                a = 0
                while a < n:
                    b = a + 1
                    while b < n and slot[p, b] == slot[p, b - 1] + 1 \
                            and (not sweep or _same_state(line, p, r, slot[p, b - 1],
                                                          slot[p, b], direction[p])):  # fmt: skip
                        if b - 1 > a:
                            d = xs[p, b] - xs[p, b - 1]
                            dp = xs[p, b - 1] - xs[p, b - 2]
                            if not (dp / RUN_RATIO < d < dp * RUN_RATIO):
                                break
                        b += 1
                    run_a[p, m] = a
                    run_b[p, m] = b
                    m += 1
                    a = b
                n_runs[p] = m
                # each run's offset candidates, named by its priors' median (a run whose
                # bands were all decided before keeps its offset), and their depths: the
                # projector column linearised in inverse depth at the band's prior
                for m in range(n_runs[p]):
                    a, b = run_a[p, m], run_b[p, m]
                    cnt = 0
                    zs = 0.0
                    decided = vertical == 1 or sweep == 1
                    # a vertical pass looks again only at runs with a line from the row
                    # before (the others it has seen)
                    active = sweep == 1
                    for t in range(a, b):
                        if decided and line[p, r, slot[p, t]] < 0:
                            decided = False
                        active = active or fresh[p, t]
                        if np.isfinite(ell[p, t]):
                            prio[cnt] = ell[p, t] - direction[p] * slot[p, t]
                            zs += zp[p, t]
                            cnt += 1
                    run_k[p, m] = NONE
                    best_err[p, m] = np.inf
                    run_fixed[p, m] = -1
                    if b - a < 2:
                        continue
                    if decided:
                        # its lines are known: the offset they share, and their depths
                        q = slot[p, a]
                        run_k[p, m] = line[p, r, q] - direction[p] * q
                        run_fixed[p, m] = SEARCH
                        for t in range(a, b):
                            cand[p, t, SEARCH] = z[p, r, slot[p, t]]
                        continue
                    if cnt == 0 or not active:
                        continue
                    kc = int(round(median_in_place(prio, cnt)))
                    run_k[p, m] = kc
                    z_run = zs / cnt
                    for t in range(a, b):
                        z0 = zp[p, t] if np.isfinite(zp[p, t]) else z_run
                        if col_known[p, t] and z0 == zp[p, t]:
                            u0, du, pz = col_u[p, t], col_du[p, t], 1.0
                        else:
                            u0, du, pz = _column(pp, rxy[p, t, 0], rxy[p, t, 1], z0)
                        for c in range(nc):
                            k = kc - SEARCH + c + direction[p] * slot[p, t]
                            v = np.nan
                            if pz > 0.0 and du != 0.0 and 0 <= k < n_lit[p]:
                                w = _inverse_depth_step(z0, u0, du, lit[p, k])
                                if w > 0.0:
                                    v = 1.0 / w
                            if np.isfinite(v):
                                # one Newton step more, at the candidate itself: linearised
                                # at a prior a line or two off, the right candidate can miss
                                # by as much as AGREE and lose to a wrong pair at the prior
                                u1, du1, pz1 = _column(pp, rxy[p, t, 0], rxy[p, t, 1], v)
                                if pz1 > 0.0 and du1 != 0.0:
                                    w = _inverse_depth_step(v, u1, du1, lit[p, k])
                                    v = 1.0 / w if w > 0.0 else np.nan
                            cand[p, t, c] = v
            # pairs of overlapping runs of the two patterns: the pair of offsets that agrees
            for m0 in range(n_runs[0]):
                if run_k[0, m0] == NONE:
                    continue
                a0, b0 = run_a[0, m0], run_b[0, m0]
                for m1 in range(n_runs[1]):
                    if run_k[1, m1] == NONE or (run_fixed[0, m0] >= 0 and run_fixed[1, m1] >= 0):
                        continue
                    a1, b1 = run_a[1, m1], run_b[1, m1]
                    lo = max(xs[0, a0], xs[1, a1])
                    hi = min(xs[0, b0 - 1], xs[1, b1 - 1])
                    if not hi > lo:
                        continue
                    # the bands compared are those of every pair of candidates; with fewer
                    # than two, every pair disagrees (inf) and none is taken
                    n_cmp, n_first = _samples(xs, zp, a0, b0, a1, b1, lo, hi, s_t, s_u, s_f)
                    if n_cmp < 2:
                        continue
                    e1 = np.inf
                    e2 = np.inf
                    c0b = -1
                    c1b = -1
                    # among the pairs that agree, the two nearest the priors
                    d1 = np.inf
                    d2 = np.inf
                    c0n = -1
                    c1n = -1
                    en = np.inf
                    for c0 in range(nc):
                        if run_fixed[0, m0] >= 0 and c0 != run_fixed[0, m0]:
                            continue
                        for c1 in range(nc):
                            if run_fixed[1, m1] >= 0 and c1 != run_fixed[1, m1]:
                                continue
                            # a pair at or above both the runner-up and AGREE changes
                            # nothing below: its median is not needed (inf stands for it)
                            e = _disagreement(cand, a0, b0, a1, b1, c0, c1, s_t, s_u, s_f,
                                              n_cmp, n_first, max(e2, AGREE), tmp)  # fmt: skip
                            if e < e1:
                                e2 = e1
                                e1 = e
                                c0b = c0
                                c1b = c1
                            elif e < e2:
                                e2 = e
                            if e < AGREE:
                                # the distance from the priors only where it is used
                                d = _prior_distance(cand, zp, c0, c1, s_t, n_cmp, n_first, tmp2)
                                if d < d1:
                                    d2 = d1
                                    d1 = d
                                    c0n = c0
                                    c1n = c1
                                    en = e
                                elif d < d2:
                                    d2 = d
                    if not (e1 < AGREE and e2 > MARGIN * e1 + RUNNER_UP):
                        # two pairs agree where the patterns' lines beat (their depths
                        # per line near 1:2): the prior tells them apart when it is near
                        # one and clearly farther from the other, or, less clearly, when
                        # the pair that agrees best is also the one nearer the prior
                        both = c0n == c0b and c1n == c1b and e1 < BOTH_AGREE \
                            and e2 > BOTH_MARGIN * e1 and d2 > d1 + BOTH_GAP  # fmt: skip
                        if not (d1 < PRIOR_REACH and d2 > d1 + PRIOR_GAP) and not both:
                            continue
                        c0b = c0n
                        c1b = c1n
                        e1 = en
                    if e1 >= best_err[0, m0] and e1 >= best_err[1, m1]:
                        continue  # both runs were taken by a pair that agreed better
                    # the exact depths of the pair taken
                    for p in range(2):
                        a, b, c = (a0, b0, c0b) if p == 0 else (a1, b1, c1b)
                        kc = run_k[0, m0] if p == 0 else run_k[1, m1]
                        pp = projs[proj_of[p]]
                        for t in range(a, b):
                            v = cand[p, t, c]
                            k = kc - SEARCH + c + direction[p] * slot[p, t]
                            if np.isfinite(v):
                                v = _depth_on_line(pp, rxy[p, t, 0], rxy[p, t, 1], lit[p, k], v,
                                                   near, far)  # fmt: skip
                            exact[p, t] = v
                    # each band that agrees with the other pattern's run takes its line (one
                    # beyond that run's ends is not checked: a run of consecutive slots can
                    # cross a depth step, where the lines beyond it are others, and their
                    # depths still look smooth)
                    for p in range(2):
                        mm, a, b, c = (m0, a0, b0, c0b) if p == 0 else (m1, a1, b1, c1b)
                        oa, ob = (a1, b1) if p == 0 else (a0, b0)
                        if e1 >= best_err[p, mm]:
                            continue
                        best_err[p, mm] = e1
                        good = np.zeros(b - a, np.bool_)
                        dev = np.zeros(b - a)
                        u = oa
                        for t in range(a, b):
                            x = xs[p, t]
                            v = exact[p, t]
                            if not (np.isfinite(v) and xs[1 - p, oa] <= x <= xs[1 - p, ob - 1]):
                                continue
                            while u + 2 < ob and xs[1 - p, u + 1] < x:
                                u += 1
                            f = (x - xs[1 - p, u]) / (xs[1 - p, u + 1] - xs[1 - p, u]) \
                                if ob - oa > 1 else 0.0  # fmt: skip
                            w = exact[1 - p, u] + f * (exact[1 - p, min(u + 1, ob - 1)]
                                                       - exact[1 - p, u])  # fmt: skip
                            dev[t - a] = abs(v - w) / v
                            good[t - a] = dev[t - a] < AGREE
                        for t in range(a, b):
                            q = slot[p, t]
                            if good[t - a] and (line[p, r, q] < 0 or not vertical):
                                line[p, r, q] = run_k[p, mm] - SEARCH + c + direction[p] * q
                                z[p, r, q] = exact[p, t]
                                resid[p, r, q] = dev[t - a] * exact[p, t]


@nb.njit(cache=True, error_model="numpy", nogil=True, **NO_CFUNC)
def _extend_rows(bands, counts, rays, projs, proj_of, lit, n_lit, direction, near, far, line, z,
                 resid, r0, r1):  # fmt: skip
    """Carry the decided runs of rows ``r0 .. r1`` outward, one band at a time.

    An undecided band next to the end of a decided run (two bands or more, its spacing
    changing by less than :data:`RUN_RATIO`; or a decided band alone, tuning rigs: +0-1
    point of the balls' coverage) takes the run's next line if the depth on
    it agrees within :data:`EXTEND_AGREE` with the other pattern's decided bands around
    it (:func:`_other_depth`): a ball's limb, whose cut and faint bands have no flow to
    name their lines.  The other pattern is what tells a wrong line apart: past a depth
    step, the next line of each pattern gives a smooth depth, but not the same one (the
    run's own depths continued do not: past a blade's end, the faint wall's or the hub's
    bands on its next lines continue its depth; development fans 43-48: 0.0-2.7 ->
    0.7-4.4 % of the depth off the blades, carried one band so, for 1-3 points of the
    balls' coverage).
    """
    for r in range(r0, r1):
        for _ in range(EXTEND_STEPS):
            changed = False
            for p in range(2):
                pp = projs[proj_of[p]]
                n = counts[p, r]
                for q in range(n):
                    if line[p, r, q] >= 0:
                        continue
                    x = bands[p, r, q, F_CENTRE]
                    # not a band with an edge inside: where a blade's edge runs along the
                    # lines, the wall's band beside it meets the blade's next line by
                    # chance in row after row (a held-out fan: all 21 such bands wrong)
                    if not np.isfinite(x) or bands[p, r, q, F_VALID] == BAND_IRREGULAR:
                        continue
                    for side in (-1, 1):
                        q1 = q + side  # the run's end
                        q2 = q + 2 * side
                        if not 0 <= q1 < n:
                            continue
                        k1 = line[p, r, q1]
                        if k1 < 0:
                            continue
                        # a run of two bands or more, or one decided band alone
                        alone = not (0 <= q2 < n and line[p, r, q2] == k1 + side * direction[p])
                        x1 = bands[p, r, q1, F_CENTRE]
                        if not alone:
                            d = abs(x - x1)
                            dp = abs(x1 - bands[p, r, q2, F_CENTRE])
                            if not dp / RUN_RATIO < d < dp * RUN_RATIO:
                                continue
                        k = k1 - side * direction[p]
                        if not 0 <= k < n_lit[p]:
                            continue
                        rx, ry = _ray_at(rays, r, x)
                        v = _depth_on_line(pp, rx, ry, lit[p, k], z[p, r, q1], near, far)
                        if not (np.isfinite(v) and abs(v - z[p, r, q1]) <= STEP * v):
                            continue
                        w, far_ = _other_depth(bands, counts, line, z, rays, 1 - p, r, x,
                                               direction[1 - p])
                        agree = EXTEND_AGREE * (FAR_AGREE if far_ else 1.0)
                        if not abs(v - w) < agree * v:  # false for NaN
                            continue
                        line[p, r, q] = k
                        z[p, r, q] = v
                        resid[p, r, q] = abs(v - w)
                        changed = True
                        break
            if not changed:
                break


@nb.njit(cache=True, error_model="numpy", nogil=True, **NO_CFUNC)
def _trace_ends(bands, counts, row_y, line, z, side, end_k, end_z, end_y, barrier, k_rows,
                stride):  # fmt: skip
    """For :func:`_fill_traces`: the first decided band of each undecided band's trace
    above it (``side`` 0) or below it (1), through undecided bands only: its line (-1:
    none, the trace breaks first), depth and image row, into ``end_*[side]``.  A band in
    a ``barrier`` cell (of the analysis grid: ``k_rows`` measured rows and ``stride``
    columns a cell) breaks the trace.  One sweep of the rows: a band's is taken over
    from its link in the row before where that is undecided too (the arrays are written
    for undecided bands only)."""
    n_rows = counts.shape[1]
    gh, gw = barrier.shape
    off = 0.5 * (stride - 1)
    step = 1 if side == 0 else -1
    for n in range(n_rows):
        r = n if side == 0 else n_rows - 1 - n
        o = r - step
        ci = min(r // k_rows, gh - 1)
        for p in range(2):
            start = 0
            for q in range(counts[p, r]):
                if line[p, r, q] >= 0:
                    continue
                end_k[side, p, r, q] = -1
                x = bands[p, r, q, F_CENTRE]
                if not (np.isfinite(x) and 0 <= o < n_rows):
                    continue
                if barrier[ci, _cell_column(x, off, stride, gw)]:
                    continue
                q2, start = _nearest_band(bands, counts, p, o, x, start)
                if q2 < 0:
                    continue
                if line[p, o, q2] >= 0:
                    end_k[side, p, r, q] = line[p, o, q2]
                    end_z[side, p, r, q] = z[p, o, q2]
                    end_y[side, p, r, q] = row_y[o]
                else:
                    end_k[side, p, r, q] = end_k[side, p, o, q2]
                    end_z[side, p, r, q] = end_z[side, p, o, q2]
                    end_y[side, p, r, q] = end_y[side, p, o, q2]


@nb.njit(cache=True, error_model="numpy", nogil=True, **NO_CFUNC)
def _fill_traces(bands, counts, rays, row_y, projs, proj_of, lit, near, far, line, z, resid,
                 end_k, end_z, end_y):  # fmt: skip
    """Give an undecided band the line of its trace where the trace is decided on both
    sides of it (``end_*``: :func:`_trace_ends` of both sides).

    A line's bands form a trace from measured row to measured row (each the nearest band
    of the next row, within :data:`LINK` of its spacing).  Where a trace's nearest
    decided bands above and below the band (within :data:`TRACE_REACH_PX`, through
    undecided bands only) have one line, and the band's depth on it lies within
    :data:`TRACE_AGREE` of theirs interpolated to its row, the band takes it (a line off
    moves a depth by 2-7 cm, 3-9 %): a ball's bands where the other pattern is cut or
    faint for a few rows, or where no flow named their lines.  Both ends are needed: a
    trace carried on from one end alone runs a fan blade's lines into the blurred edge
    beyond the blade.  Near lines seen standing still the traces break
    (:func:`_trace_ends`): a fan's hub, at its blades' depth, is the same surface to them.
    """
    for r in range(counts.shape[1]):
        for p in range(2):
            pp = projs[proj_of[p]]
            for q in range(counts[p, r]):
                if line[p, r, q] >= 0:
                    continue
                k = end_k[0, p, r, q]
                if k < 0 or end_k[1, p, r, q] != k:
                    continue
                if not (abs(end_y[0, p, r, q] - row_y[r]) <= TRACE_REACH_PX
                        and abs(end_y[1, p, r, q] - row_y[r]) <= TRACE_REACH_PX):  # fmt: skip
                    continue
                # the depth between the two ends, linear in the image row
                y0 = end_y[0, p, r, q]
                f = (row_y[r] - y0) / (end_y[1, p, r, q] - y0)
                zi = end_z[0, p, r, q] + f * (end_z[1, p, r, q] - end_z[0, p, r, q])
                rx, ry = _ray_at(rays, r, bands[p, r, q, F_CENTRE])
                v = _depth_on_line(pp, rx, ry, lit[p, k], zi, near, far)
                if abs(v - zi) < TRACE_AGREE * v:
                    line[p, r, q] = k
                    z[p, r, q] = v
                    resid[p, r, q] = FLOOR * v


@nb.njit(cache=True, error_model="numpy", **INTERNAL)
def _nearest_band(bands, counts, p, o, x, start):
    """The band of row ``o`` nearest to column ``x`` if it lies within :data:`LINK` of its
    spacing (the same line, a row apart), else -1; and where the search for a larger
    ``x`` may start (centres are in column order: the bands of a row are matched in one
    sweep)."""
    best = -1
    dist = np.inf
    for q in range(start, counts[p, o]):
        d = abs(bands[p, o, q, F_CENTRE] - x)
        if d < dist:  # false for a NaN centre
            dist = d
            best = q
        elif d > dist:
            break
    if best < 0:
        return -1, start
    if not dist < LINK * _spacing(bands, p, o, best, counts[p, o]):
        return -1, best
    return best, best


@nb.njit(cache=True, error_model="numpy", **INTERNAL)
def _other_depth(bands, counts, line, z, rays, p, r, x, direction):
    """Pattern ``p``'s depth at column ``x`` of row ``r`` from three neighbouring decided
    bands of one run: where the circle through their surface points meets the camera
    ray of ``x`` (:func:`_circle_depth`), between them or carried on for at most one of
    their spacings (:data:`FAR_REACH` where they change towards ``x``, a limb); NaN
    without such bands, or where the ray misses the circle (past a ball's limb).  Also
    whether it was carried on further than one spacing."""
    n = counts[p, r]
    best = -1
    dist = np.inf
    far = False
    for q in range(n - 2):
        if line[p, r, q] < 0 or line[p, r, q + 1] != line[p, r, q] + direction \
                or line[p, r, q + 2] != line[p, r, q] + 2 * direction:  # fmt: skip
            continue
        xa = bands[p, r, q, F_CENTRE]
        xb = bands[p, r, q + 1, F_CENTRE]
        xc = bands[p, r, q + 2, F_CENTRE]
        if not (xb > xa and xc > xb):
            continue
        if xa <= x <= xc:
            d = 0.0
        else:
            d = xa - x if x < xa else x - xc
            # the spacing next to x, and the one beyond it
            near, beyond = (xb - xa, xc - xb) if x < xa else (xc - xb, xb - xa)
            s = min(near, beyond)
            if d > FAR_REACH * s or (d > s and abs(near / beyond - 1.0) < LIMB_CHANGE):
                continue
        if d < dist:
            dist = d
            best = q
            far = d > min(xb - xa, xc - xb)
    if best < 0:
        return np.nan, False
    # the three points, ordered so that the last is the one beside x where x lies beyond
    # them (of the circle's two crossings with the ray, the one nearer its depth is taken)
    qa, qc = (best + 2, best) if x < bands[p, r, best, F_CENTRE] else (best, best + 2)
    ax, ay = _ray_at(rays, r, bands[p, r, qa, F_CENTRE])
    bx, by = _ray_at(rays, r, bands[p, r, best + 1, F_CENTRE])
    cx, cy = _ray_at(rays, r, bands[p, r, qc, F_CENTRE])
    rx, _ = _ray_at(rays, r, x)
    return _circle_depth(ax, z[p, r, qa], bx, z[p, r, best + 1], cx, z[p, r, qc],
                         (ay + by + cy) / 3.0, rx), far


@nb.njit(cache=True, error_model="numpy", inline="always", **INTERNAL)
def _cell_column(x, off, stride, gw):
    """The analysis grid column of image column ``x`` (``off``: the first cell centre's
    column; clamped to the ``gw`` columns)."""
    return min(max(int(round((x - off) / stride)), 0), gw - 1)


@nb.njit(cache=True, error_model="numpy", inline="always", **INTERNAL)
def _ray_at(rays, r, x):
    """The camera ray ``(rx, ry)`` of sub-pixel column ``x`` of measured row ``r``."""
    c0 = min(int(x), rays.shape[1] - 2)
    t = x - c0
    rx = rays[r, c0, 0] + t * (rays[r, c0 + 1, 0] - rays[r, c0, 0])
    ry = rays[r, c0, 1] + t * (rays[r, c0 + 1, 1] - rays[r, c0, 1])
    return rx, ry


@nb.njit(cache=True, error_model="numpy", **INTERNAL)
def _circle_depth(ax, az, bx, bz, cx, cz, ry, rx):
    """Depth at which the camera ray of ray x ``rx`` meets the circle through three
    surface points of a row (ray x and depth each: ``a``, ``b``, ``c``; ``ry`` their
    rays' mean y), on the side of the last point; NaN where it misses.

    A row's rays lie in one plane through the camera (nearly: a lens bends it a
    little), and that plane cuts a sphere in a circle and a plane in a line (a circle
    of infinite radius): exact on both.  On the evaluation's balls the other pattern's
    depth so predicted at a limb band's next line is 0.07-0.08 % off in the median,
    where a parabola in the image column was 0.5-0.6 % off (more than
    :data:`EXTEND_AGREE`, so the limb's lines were not carried on).
    """
    # in-plane coordinates: x along the row, the depth axis stretched by the plane's tilt
    s = math.sqrt(1.0 + ry * ry)
    x1, y1 = ax * az, az * s
    x2, y2 = bx * bz, bz * s
    x3, y3 = cx * cz, cz * s
    dx, dy = rx, s  # the ray: t * (dx, dy), t its depth
    det = 2.0 * (x1 * (y2 - y3) + x2 * (y3 - y1) + x3 * (y1 - y2))
    scale = (x3 - x1) ** 2 + (y3 - y1) ** 2
    if abs(det) < 1e-9 * scale:
        # in line: the ray meets the line through the last two points
        ex, ey = x3 - x2, y3 - y2
        den = dx * ey - dy * ex
        if den == 0.0:
            return np.nan
        return (x2 * ey - y2 * ex) / den
    a1 = x1 * x1 + y1 * y1
    a2 = x2 * x2 + y2 * y2
    a3 = x3 * x3 + y3 * y3
    ux = (a1 * (y2 - y3) + a2 * (y3 - y1) + a3 * (y1 - y2)) / det
    uy = (a1 * (x3 - x2) + a2 * (x1 - x3) + a3 * (x2 - x1)) / det
    rho2 = (x3 - ux) ** 2 + (y3 - uy) ** 2
    a = dx * dx + dy * dy
    b = -2.0 * (dx * ux + dy * uy)
    c = ux * ux + uy * uy - rho2
    disc = b * b - 4.0 * a * c
    if disc < 0.0:
        return np.nan
    root = math.sqrt(disc)
    t1 = (-b - root) / (2.0 * a)
    t2 = (-b + root) / (2.0 * a)
    return t1 if abs(t1 - cz) <= abs(t2 - cz) else t2


@nb.njit(cache=True, error_model="numpy", **INTERNAL)
def _same_state(line, p, r, q0, q1, direction):
    """Whether slots ``q0`` and ``q1`` of row ``r`` are both undecided, or both decided
    with lines of one run (the same offset)."""
    k0 = line[p, r, q0]
    k1 = line[p, r, q1]
    if k0 < 0 or k1 < 0:
        return k0 < 0 and k1 < 0
    return k0 - direction * q0 == k1 - direction * q1


@nb.njit(cache=True, error_model="numpy", **INTERNAL)
def _spacing(bands, p, r, q, n):
    """The spacing of band ``q`` of row ``r`` to its neighbours (camera px; inf alone)."""
    c = bands[p, r, q, F_CENTRE]
    s = 0.0
    k = 0
    if q > 0 and np.isfinite(bands[p, r, q - 1, F_CENTRE]):
        s += c - bands[p, r, q - 1, F_CENTRE]
        k += 1
    if q + 1 < n and np.isfinite(bands[p, r, q + 1, F_CENTRE]):
        s += bands[p, r, q + 1, F_CENTRE] - c
        k += 1
    return s / k if k else np.inf


@nb.njit(cache=True, error_model="numpy", **INTERNAL)
def _same_line(bands, counts, line, p, o, x, start):
    """The decided band of row ``o`` nearest to column ``x`` if it lies within
    :data:`LINK` of its spacing (the same line, a row apart), else -1; and where the
    search for a larger ``x`` may start (centres are in column order: the bands of a
    row are matched in one sweep)."""
    q, start = _nearest_band(bands, counts, p, o, x, start)
    if q >= 0 and line[p, o, q] < 0:
        return -1, q
    return q, start


@nb.njit(cache=True, error_model="numpy", **INTERNAL)
def _linkable(bands, counts, line, r, o):
    """Whether row ``r`` has an undecided band with a decided one of its
    pattern in row ``o`` nearby (a vertical pass has something to do there)."""
    if not 0 <= o < counts.shape[1]:
        return False
    for p in range(2):
        start = 0
        for q in range(counts[p, r]):
            x = bands[p, r, q, F_CENTRE]
            if line[p, r, q] >= 0 or not np.isfinite(x):
                continue
            match, start = _same_line(bands, counts, line, p, o, x, start)
            if match >= 0:
                return True
    return False


@nb.njit(cache=True, error_model="numpy", **INTERNAL)
def _samples(xs, zp, a0, b0, a1, b1, lo, hi, s_t, s_u, s_f):
    """The bands at which :func:`_disagreement` compares two runs' depths: up to
    :data:`SAMPLES` bands of each inside ``lo .. hi`` that have a prior (``zp``: a run
    can reach from a moving surface onto a still one), evenly spread.  Into ``s_t``
    their slots, ``s_u`` the other run's band before them and ``s_f`` their share of
    the way to its next (where it has one); returns how many, and how many of them
    are the first run's.  The same for every pair of candidates: found once per pair
    of runs, not for each of the 25."""
    n = 0
    n_first = 0
    for p in range(2):
        a, b = (a0, b0) if p == 0 else (a1, b1)
        oa, ob = (a1, b1) if p == 0 else (a0, b0)
        k = 0
        for t in range(a, b):
            if lo <= xs[p, t] <= hi and np.isfinite(zp[p, t]):
                k += 1
        if k > 0:
            use = min(k, SAMPLES)
            u = oa
            s = 0
            e = -1
            for t in range(a, b):
                if not (lo <= xs[p, t] <= hi and np.isfinite(zp[p, t])):
                    continue
                e += 1
                if s >= use or e != ((s * (k - 1)) // (use - 1) if use > 1 else 0):
                    continue
                s += 1
                x = xs[p, t]
                while u + 2 < ob and xs[1 - p, u + 1] < x:
                    u += 1
                s_t[n] = t
                s_u[n] = u
                if ob - oa > 1:
                    s_f[n] = (x - xs[1 - p, u]) / (xs[1 - p, u + 1] - xs[1 - p, u])
                n += 1
        if p == 0:
            n_first = n
    return n, n_first


@nb.njit(cache=True, error_model="numpy", **INTERNAL)
def _disagreement(cand, a0, b0, a1, b1, c0, c1, s_t, s_u, s_f, n, n_first, bound, tmp):
    """Median relative disagreement of two runs' depths (candidates ``c0``, ``c1``) at
    the ``n`` bands :func:`_samples` chose, against the other run interpolated; inf
    where a depth is missing, and where the median is at least ``bound`` (told from how
    many lie below it, without sorting them: most candidate pairs are a line off)."""
    for i in range(n):
        p = 0 if i < n_first else 1
        c, oc = (c0, c1) if p == 0 else (c1, c0)
        oa, ob = (a1, b1) if p == 0 else (a0, b0)
        t = s_t[i]
        u = s_u[i]
        v = cand[p, t, c]
        if ob - oa > 1:
            w = cand[1 - p, u, oc] + s_f[i] * (cand[1 - p, u + 1, oc] - cand[1 - p, u, oc])
        else:
            w = cand[1 - p, u, oc]
        if not (np.isfinite(v) and np.isfinite(w)):
            return np.inf
        tmp[i] = abs(v - w) / v
    # the middle value (odd n) or the lower of the two middle ones is at least bound when
    # no more values than those below it lie below bound (the mean of two values at least
    # bound is too: rounding is monotone)
    below = 0
    for i in range(n):
        if tmp[i] < bound:
            below += 1
    if below <= (n >> 1) - (1 - (n & 1)):
        return np.inf
    return median_in_place(tmp, n)


@nb.njit(cache=True, error_model="numpy", **INTERNAL)
def _prior_distance(cand, zp, c0, c1, s_t, n, n_first, tmp):
    """Median relative distance of two runs' depths (candidates ``c0``, ``c1``) at the
    ``n`` bands :func:`_samples` chose from their priors (absolute value)."""
    for i in range(n):
        p = 0 if i < n_first else 1
        t = s_t[i]
        v = cand[p, t, c0 if p == 0 else c1]
        tmp[i] = (v - zp[p, t]) / zp[p, t]
    return abs(median_in_place(tmp, n))


@nb.njit(cache=True, error_model="numpy", **INTERNAL)
def _row_order(bands, counts, line, r, ps, qs):
    """The triangulated bands of both patterns in row ``r``, in column order: their
    patterns and slots into ``ps`` and ``qs``; returns how many."""
    n = 0
    for p in range(2):
        for q in range(counts[p, r]):
            if line[p, r, q] < 0:
                continue
            x = bands[p, r, q, F_CENTRE]
            t = n
            while t > 0 and bands[ps[t - 1], r, qs[t - 1], F_CENTRE] > x:
                ps[t] = ps[t - 1]
                qs[t] = qs[t - 1]
                t -= 1
            ps[t] = p
            qs[t] = q
            n += 1
    return n


@nb.njit(cache=True, error_model="numpy", **NO_CFUNC)
def _moving_bands(bands, counts, line, z, k_rows, stride, seeds, still, hops):
    """Which triangulated bands lie on a moving surface (``(2, rows, max_bands)`` bool).

    Those in a ``seeds`` cell, and those that a chain of at most ``hops`` bands of one
    surface links to one through no ``still`` cell: a ball's limb and a cut or printed
    band have a centre (so a line and a depth) but no sweep that shows them moving.
    Bands of one surface are neighbours along a row (either pattern) at most
    :data:`GAP` of their spacing apart, or the same line in the next measured row, with
    depths within :data:`STEP` of each other: the wall behind a ball's limb is not one,
    and the still lines of a wall or a fan's hub stop a chain.
    """
    n_rows = counts.shape[1]
    mb = bands.shape[2]
    gh, gw = seeds.shape
    off = 0.5 * (stride - 1)
    kk = 2 * mb
    # per row, the triangulated bands of both patterns in column order
    tx = np.empty((n_rows, kk))
    tz = np.empty((n_rows, kk))
    ts = np.empty((n_rows, kk))
    tp = np.empty((n_rows, kk), np.int64)
    tq = np.empty((n_rows, kk), np.int64)
    tc = np.empty((n_rows, kk), np.int64)  # the band's cell column
    nt = np.zeros(n_rows, np.int64)
    for r in range(n_rows):
        n = _row_order(bands, counts, line, r, tp[r], tq[r])
        nt[r] = n
        for t in range(n):
            p, q = tp[r, t], tq[r, t]
            tx[r, t] = bands[p, r, q, F_CENTRE]
            tz[r, t] = z[p, r, q]
            ts[r, t] = _spacing(bands, p, r, q, counts[p, r])
            tc[r, t] = _cell_column(tx[r, t], off, stride, gw)
    on = np.zeros((2, n_rows, mb), np.bool_)
    dist = np.full((n_rows, kk), -1, np.int64)  # links from a seed; -1: not reached
    queue = np.empty(n_rows * kk, np.int64)
    top = 0
    for r in range(n_rows):
        i = min(r // k_rows, gh - 1)
        for t in range(nt[r]):
            if seeds[i, tc[r, t]]:
                dist[r, t] = 0
                queue[top] = r * kk + t
                top += 1
    head = 0
    while head < top:
        r = queue[head] // kk
        t = queue[head] % kk
        head += 1
        p = tp[r, t]
        on[p, r, tq[r, t]] = True
        x = tx[r, t]
        zt = tz[r, t]
        s = ts[r, t]
        k = line[p, r, tq[r, t]]
        if dist[r, t] >= hops:
            continue
        for r2, lo, hi in ((r, t - 1, t), (r, t + 1, t + 2), (r - 1, 0, 0), (r + 1, 0, 0)):
            if not 0 <= r2 < n_rows:
                continue
            if r2 != r:
                # the same line a row apart: among the bands within half a spacing
                lo = 0
                hi = nt[r2]
                while lo < hi:
                    mid = (lo + hi) // 2
                    if tx[r2, mid] < x - 0.5 * s:
                        lo = mid + 1
                    else:
                        hi = mid
                hi = lo
                while hi < nt[r2] and tx[r2, hi] <= x + 0.5 * s:
                    hi += 1
            i2 = min(r2 // k_rows, gh - 1)
            for t2 in range(max(lo, 0), min(hi, nt[r2])):
                if dist[r2, t2] >= 0 or still[i2, tc[r2, t2]]:
                    continue
                if abs(tz[r2, t2] - zt) > STEP * zt:
                    continue
                if r2 == r:
                    if abs(tx[r2, t2] - x) > GAP * max(s, ts[r2, t2]):
                        continue
                elif tp[r2, t2] != p or line[p, r2, tq[r2, t2]] != k:
                    continue
                dist[r2, t2] = dist[r, t] + 1
                queue[top] = r2 * kk + t2
                top += 1
    return on


@nb.njit(cache=True, error_model="numpy", **NO_CFUNC)
def _cells(bands, counts, line, z, resid, k_rows, stride, moving, on_moving, barrier, rays,
           projs, proj_of, lit, n_lit, depth_grid, std_grid):  # fmt: skip
    """Depth of the cells on a moving surface from the triangulated bands along their row:
    any cell of ``moving``, and any other between two bands of ``on_moving`` (unless a band
    between them splits them: :func:`_split_pairs`) or on the light of one
    (:data:`EXTENT`), or past one towards a limb (:func:`_limb_depth`) outside the
    ``barrier`` of still lines."""
    gh, gw = depth_grid.shape
    mb = bands.shape[2]
    off = 0.5 * (stride - 1)
    sx = np.empty(2 * mb)
    sz = np.empty(2 * mb)
    sr = np.empty(2 * mb)
    ss = np.empty(2 * mb)
    sm = np.empty(2 * mb, np.bool_)
    sa = np.empty(2 * mb)
    sb = np.empty(2 * mb)
    sp = np.empty(2 * mb, np.int64)
    sq = np.empty(2 * mb, np.int64)
    free = np.empty((2, 2 * mb))
    split = np.empty(2 * mb, np.bool_)
    ptr = np.empty(2, np.int64)
    written = 0
    for i in range(gh):
        r = i * k_rows
        if r >= counts.shape[1]:
            break
        # the row's triangulated bands of both patterns, in column order
        n = _row_order(bands, counts, line, r, sp, sq)
        for t in range(n):
            p, q = sp[t], sq[t]
            sx[t] = bands[p, r, q, F_CENTRE]
            sa[t] = bands[p, r, q, F_START]
            sb[t] = bands[p, r, q, F_END]
            sz[t] = z[p, r, q]
            sr[t] = resid[p, r, q]
            ss[t] = _spacing(bands, p, r, q, counts[p, r])
            sm[t] = on_moving[p, r, q]
        if n == 0:
            continue
        _free_sides(bands, counts, line, r, sx, n, ptr, free)
        _split_pairs(bands, counts, line, r, sx, sz, n, rays, projs, proj_of, lit, n_lit, split)
        t = 0
        for j in range(gw):
            x = j * stride + off
            while t < n and sx[t] < x:
                t += 1
            # a cell outside the moving ones takes bands of the moving surface only
            only = not moving[i, j]
            v = np.nan
            e = 0.0
            if 0 < t < n and (not only or (sm[t - 1] and sm[t])):
                za, zb = sz[t - 1], sz[t]
                gap = sx[t] - sx[t - 1]
                if gap <= GAP * max(ss[t - 1], ss[t]) and abs(zb - za) <= STEP * za \
                        and not (only and split[t]):  # fmt: skip
                    f = (x - sx[t - 1]) / gap
                    v = za + f * (zb - za)
                    e = max(sr[t - 1], sr[t])
            if not np.isfinite(v):
                # beyond the row's last band on a side, or next to a depth edge: close to
                # the nearest band, along the line through it and the next band of its
                # surface (its own depth alone if there is none)
                best = np.inf
                for u, nxt in ((t - 1, t - 2), (t, t + 1)):
                    if not (0 <= u < n and abs(sx[u] - x) <= REACH * ss[u]):
                        continue
                    if only and not (sm[u] and sa[u] - EXTENT <= x <= sb[u] + EXTENT):
                        continue
                    if abs(sx[u] - x) >= best:
                        continue
                    best = abs(sx[u] - x)
                    v = sz[u]
                    e = sr[u]
                    # (a band of the other pattern a fraction of a pixel away gives no
                    # slope: the next one a quarter spacing away at least)
                    step = nxt - u
                    while 0 <= nxt < n and abs(sx[nxt] - sx[u]) < 0.25 * ss[u]:
                        nxt += step
                    if 0 <= nxt < n and abs(sx[nxt] - sx[u]) <= GAP * max(ss[u], ss[nxt]) \
                            and abs(sz[nxt] - sz[u]) <= STEP * sz[u] \
                            and (sm[nxt] or not only):  # fmt: skip
                        w = sz[u] + (x - sx[u]) * (sz[nxt] - sz[u]) / (sx[nxt] - sx[u])
                        if abs(w - sz[u]) <= STEP * sz[u]:
                            v = w
                            e = max(sr[u], sr[nxt])
            if not np.isfinite(v) and not barrier[i, j]:
                for u in (t - 1, t):
                    # (the spacing next to the band, away from x, is at most twice its mean)
                    if 0 <= u < n and sm[u] and abs(x - sx[u]) <= 2.0 * LIMB_REACH * ss[u]:
                        w = _limb_depth(bands, counts, line, z, rays, r, sp[u], sq[u], x,
                                        free[int(x > sx[u]), u])  # fmt: skip
                        if np.isfinite(w):
                            v = w
                            e = sr[u]
                            break
            if np.isfinite(v):
                depth_grid[i, j] = v
                std_grid[i, j] = math.sqrt((FLOOR * v) ** 2 + e * e)
                written += 1
    return written


@nb.njit(cache=True, error_model="numpy", **INTERNAL)
def _split_pairs(bands, counts, line, r, sx, sz, n, rays, projs, proj_of, lit, n_lit, split):
    """For each pair of neighbouring triangulated bands of row ``r`` (``t - 1`` and ``t``),
    whether a band between them with a centre but no line says that the surface does not
    go on from one to the other: at the depth interpolated between them its projector
    column lies more than :data:`SPLIT` of a line from its pattern's nearest line (a
    wall's line between two blades at one depth; on one surface, a band the decisions
    left undecided still lies on a line at that depth)."""
    width = rays.shape[1]
    for t in range(n):
        split[t] = False
    for o in range(2):
        pp = projs[proj_of[o]]
        t = 0
        for q in range(counts[o, r]):
            x = bands[o, r, q, F_CENTRE]
            if line[o, r, q] >= 0 or not (np.isfinite(x) and 0.0 <= x <= width - 1):
                continue
            while t < n and sx[t] < x:
                t += 1
            if t == 0 or t == n or split[t]:
                continue
            v = sz[t - 1] + (x - sx[t - 1]) / (sx[t] - sx[t - 1]) * (sz[t] - sz[t - 1])
            rx, ry = _ray_at(rays, r, x)
            u, _, pz = _column(pp, rx, ry, v)
            k = _line_coordinate(lit[o], n_lit[o], u) if pz > 0.0 else np.nan
            if np.isfinite(k) and abs(k - round(k)) > SPLIT:
                split[t] = True


@nb.njit(cache=True, error_model="numpy", **INTERNAL)
def _free_sides(bands, counts, line, r, sx, n, nxt, free):
    """For each of row ``r``'s ``n`` triangulated bands (centres ``sx``, in column order),
    the distance to the nearest band of either pattern on its left (``free[0]``) and on
    its right (``free[1]``) if that band has a centre but no line; infinite otherwise.
    ``nxt``: scratch, one per pattern."""
    nxt[0] = 0
    nxt[1] = 0
    for t in range(n):
        x = sx[t]
        dl = np.inf
        dr = np.inf
        kl = 0
        kr = 0
        for o in range(2):
            m = counts[o, r]
            # pattern o's first band right of x (centres in column order; NaN ones passed)
            while nxt[o] < m and not bands[o, r, nxt[o], F_CENTRE] > x:
                nxt[o] += 1
            if nxt[o] < m and bands[o, r, nxt[o], F_CENTRE] - x < dr:
                dr = bands[o, r, nxt[o], F_CENTRE] - x
                kr = line[o, r, nxt[o]]
            u = nxt[o] - 1
            while u >= 0 and not bands[o, r, u, F_CENTRE] < x:
                u -= 1
            if u >= 0 and x - bands[o, r, u, F_CENTRE] < dl:
                dl = x - bands[o, r, u, F_CENTRE]
                kl = line[o, r, u]
        free[0, t] = dl if kl < 0 else np.inf
        free[1, t] = dr if kr < 0 else np.inf


@nb.njit(cache=True, error_model="numpy", **INTERNAL)
def _limb_depth(bands, counts, line, z, rays, r, p, q, x, free):
    """Depth at column ``x`` past band ``q`` of pattern ``p`` (row ``r``) towards a limb,
    or NaN: on the circle through it and the next two bands of its run away from ``x``
    (decided on consecutive lines, none cut), if their two spacings differ by
    :data:`LIMB_CHANGE` or more and the circle ends within :data:`LIMB_CLOSE` times the
    band's spacing to the next of them, for :data:`LIMB_REACH` times it at most, and
    half-way at most to the nearest band without a line beyond the band (``free``)."""
    xu = bands[p, r, q, F_CENTRE]
    dq = -1 if x > xu else 1
    q1 = q + dq
    q2 = q + 2 * dq
    if not (0 <= q1 < counts[p, r] and 0 <= q2 < counts[p, r]):
        return np.nan
    k0, k1, k2 = line[p, r, q], line[p, r, q1], line[p, r, q2]
    if k1 < 0 or k2 < 0 or abs(k1 - k0) != 1 or k2 - k1 != k1 - k0:
        return np.nan
    for b in (q, q1, q2):
        if bands[p, r, b, F_VALID] == BAND_CUT:  # its centre would bend the circle
            return np.nan
    x1 = bands[p, r, q1, F_CENTRE]
    x2 = bands[p, r, q2, F_CENTRE]
    near = abs(xu - x1)
    beyond = abs(x1 - x2)
    d = abs(x - xu)
    if not (beyond > 0.0 and d <= LIMB_REACH * near and d <= 0.5 * free
            and abs(near / beyond - 1.0) >= LIMB_CHANGE):  # fmt: skip
        return np.nan
    ax, ay = _ray_at(rays, r, x2)
    bx, by = _ray_at(rays, r, x1)
    cx, cy = _ray_at(rays, r, xu)
    ry = (ay + by + cy) / 3.0
    za, zb, zc = z[p, r, q2], z[p, r, q1], z[p, r, q]
    # the circle must end near: past a plane's last band the surface may go on or not
    # (unless that lies past the image's border, up to which the band's surface goes on)
    end = xu - dq * LIMB_CLOSE * near
    if 0.0 <= end <= rays.shape[1] - 2:
        ex, _ = _ray_at(rays, r, end)
        if np.isfinite(_circle_depth(ax, za, bx, zb, cx, zc, ry, ex)):
            return np.nan
    rx, _ = _ray_at(rays, r, x)
    w = _circle_depth(ax, za, bx, zb, cx, zc, ry, rx)
    return w if abs(w - zc) <= STEP * zc else np.nan  # false for NaN


def _share(mask: np.ndarray, window: int) -> np.ndarray:
    """Per cell, the share of the ``window`` x ``window`` cells around it in ``mask``
    (cells beyond the grid count as outside it)."""
    return cv2.blur(mask.astype(np.float32), (window, window), borderType=cv2.BORDER_CONSTANT)


def warm_up() -> None:
    """Compile the kernels on a tiny problem (no rig needed)."""
    bands = np.full((2, 2, 4, 10), np.nan)
    bands[:, :, :3, F_CENTRE] = [[[2.0, 6.0, 10.0]] * 2] * 2
    counts = np.full((2, 2), 3, np.int64)
    line_centred(bands, counts)
    rays = np.zeros((2, 16, 2))
    rays[..., 0] = np.linspace(-0.1, 0.1, 16)
    projs = np.zeros((1, 17 + LENS_COEFFICIENTS))
    projs[0, [0, 4, 8]] = 1.0
    projs[0, 9] = -0.1
    projs[0, [12, 15]] = 100.0
    lit = np.tile(np.arange(0.0, 40.0, 4.0), (2, 1))
    n_lit = np.array([10, 10], np.int64)
    zeros = np.zeros(2, np.int64)
    prior = np.full((2, 4), 0.5)
    line = np.full((2, 2, 4), -1, np.int64)
    z = np.full((2, 2, 4), np.nan)
    resid = np.full((2, 2, 4), np.nan)
    for vertical, order in ((0, 1), (1, 1), (1, -1)):
        _decide_rows(bands, counts, rays, projs, zeros, lit, n_lit, np.ones(2, np.int64), prior,
                     1, 4, 0.3, 3.0, line, z, resid, vertical, order, 0, 2)  # fmt: skip
    _extend_rows(bands, counts, rays, projs, zeros, lit, n_lit, np.ones(2, np.int64), 0.3, 3.0,
                 line, z, resid, 0, 2)  # fmt: skip
    ends = (np.empty((2, 2, 2, 4), np.int64), np.empty((2, 2, 2, 4)), np.empty((2, 2, 2, 4)))
    for side in range(2):
        _trace_ends(bands, counts, np.array([0.0, 4.0]), line, z, side, *ends,
                    np.zeros((2, 4), np.bool_), 1, 4)  # fmt: skip
    _fill_traces(bands, counts, rays, np.array([0.0, 4.0]), projs, zeros, lit, 0.3, 3.0, line, z,
                 resid, *ends)  # fmt: skip
    grid = np.full((2, 4), np.nan, np.float32)  # the pipeline's depth and error grids
    moving = np.ones((2, 4), np.bool_)
    on = _moving_bands(bands, counts, line, z, 1, 4, moving, ~moving, HOPS)
    _cells(bands, counts, line, z, resid, 1, 4, moving, on, moving, rays, projs, zeros, lit, n_lit,
           grid, grid.copy())  # fmt: skip
