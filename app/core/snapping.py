"""Line intervals that know the projected lines sit on whole projector columns.

A pattern's nominal line centres (``offset + k * pitch`` for a uniform one) fall
between projector columns; the pattern lights whole columns
(:func:`~.patterns.lit_columns`), so each line's true centre is its nominal one
moved by up to half a column.  Neighbouring lines of a uniform pattern are then
``floor(pitch)`` or ``ceil(pitch)`` columns apart, not ``pitch``: with a pitch of
25.8 columns, most spacings are 26 (0.7 % long) and every fifth or sixth is 25
(3 % short).  A band's interval, the mean of its two spacings, inherits this: its
mean is right but its median is 0.5-0.7 % long, and the flows and the line width
read against it with it.  Measured on rendered boards against the renderer's
truth, the interval of a band is within -1.4 to +0.9 % (p10-p90) as measured and
within 0.3 % once the snapping is taken out.  An exp2 pattern's spacings change
from line to line anyway, and its snapping makes them 1-5 % off, in no order.

Which lines a run of bands shows is not known.  It is found per run of a row,
among candidates: the index of the run's first line, each of which predicts the
true spacings of the run's lines.  For each, the run's log spacings less the
predicted ones should follow a smooth trend (a straight line, a parabola for six
spacings and more).  The fit of
each candidate is pooled with the runs of the same lines in :data:`REACH_ROWS`
rows above and below (bands are paired with the nearest centre of the next row).
A run keeps its intervals when no candidate fits clearly better (:data:`MIN_GAIN`)
than no snapping at all: a pattern drawn without it, or a run too short to tell.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

from .bands import BAND_VALID, F_CENTRE, F_INTERVAL, F_VALID, N_FIELDS, nearest_partners
from .geometry import project_to_projector, undistort_pixels
from .kernel_options import INTERNAL, NO_CFUNC
from .patterns import line_centres, line_columns
from .rig import CameraModel, Pattern, ProjectorModel

#: rows above and below whose runs of the same lines are pooled into a run's fit
REACH_ROWS = 3
#: a candidate is used only when its pooled residual is below this share of no snapping's
MIN_GAIN = 0.5
#: a run is corrected only when it has this many spacings: in a shorter one (a ball's
#: rows, towards its limb) a phase that puts a whole-column step where the trend bends
#: fits better than none (chosen on the tuning rigs: 5 made a ball 13.4 -> 14.9 mm, 8
#: and 12 left a tilted board at 2.7 and a board at 1.9 mm, against 1.4 and 0.9 with 6)
MIN_SPACINGS = 6
#: neighbouring spacings of one run differ by less than this factor (else a new run)
RUN_RATIO = 1.33
#: the residual of a candidate that puts a run's lines past the pattern's ends
IMPOSSIBLE = 1e30
#: a band's partner in the next row is the nearest centre within this share of its
#: interval
LINK_REACH = 0.25


def column_direction(camera: CameraModel, projector: ProjectorModel, depth: float) -> int:
    """+1 where the projector columns a camera row sees increase along it, else -1.

    A projector mounted upside down, or seen in a mirror, lights columns that
    decrease from left to right in the camera; its lines then meet a run of bands
    in the other order.

    Parameters
    ----------
    camera, projector : CameraModel, ProjectorModel
    depth : float
        Depth (m) of the point seen at the image centre that the test projects.

    Returns
    -------
    int
        +1 or -1.
    """
    cx, cy = 0.5 * camera.width, 0.5 * camera.height
    xy = undistort_pixels(camera.K, camera.dist, np.array([[cx - 8.0, cy], [cx + 8.0, cy]]))
    points = np.column_stack([xy * depth, np.full(2, depth)])
    u = project_to_projector(projector, points)[:, 0]
    return 1 if u[1] >= u[0] else -1


@dataclass(frozen=True)
class LineSnapping:
    """One pattern's snapping as tables over candidates (rows: the index ``c`` of a run's
    first line) and the run's spacings.

    Attributes
    ----------
    log_d : numpy.ndarray
        ``(C + 1, n)``: log of the true spacing (projector px) after a run's
        ``j``-th band for candidate ``c``; NaN past the pattern's ends; the last
        row, 0, is "no snapping".
    sums : numpy.ndarray
        ``(4, C + 1, n + 1)``: running sums over ``j < m`` of ``log_d``,
        ``j log_d``, ``j^2 log_d`` and ``log_d^2``.
    factor : numpy.ndarray
        ``(C, n)``: nominal over true spacing.
    direction : int
        :func:`column_direction`: the run's band ``j`` shows line ``c + direction * j``.
    """

    log_d: np.ndarray
    sums: np.ndarray
    factor: np.ndarray
    direction: int

    @staticmethod
    def of(pattern: Pattern, width: int, direction: int,
           bands_per_row: int) -> LineSnapping | None:  # fmt: skip
        """The tables of one pattern, for runs of up to ``bands_per_row`` bands.

        Parameters
        ----------
        pattern : Pattern
        width : int
            The projector's width (px).
        direction : int
            :func:`column_direction`.
        bands_per_row : int
            Width of the detector's band table.

        Returns
        -------
        LineSnapping or None
            ``None`` where every line sits on its nominal centre (a uniform
            pattern with a whole pitch and offset), so there is nothing to take out.
        """
        n = bands_per_row - 1
        if n < 1:
            return None
        j = np.arange(n + 1)
        nominal_c = line_centres(pattern, width)
        cols = line_columns(pattern, width)
        # a line cut by the projector's edge is centred on what is left of it: such
        # lines are not used (no candidate puts a run on them)
        whole = (cols[:, 0] >= 0) & (cols[:, 1] <= width - 1)
        true_c = np.where(whole, 0.5 * (cols[:, 0] + cols[:, 1]), np.nan)
        if nominal_c.size < 2:
            return None
        lines = np.arange(nominal_c.size)[:, None] + direction * j[None, :]
        inside = (lines >= 0) & (lines < nominal_c.size)
        at = np.clip(lines, 0, nominal_c.size - 1)
        with np.errstate(invalid="ignore"):
            true = np.where(inside[:, 1:] & inside[:, :-1], np.abs(np.diff(true_c[at], axis=1)),
                            np.nan)  # fmt: skip
            nominal = np.abs(np.diff(nominal_c[at], axis=1))
            off = np.abs(true / nominal - 1)
        if not np.any(off > 1e-9):
            return None  # every line on its nominal centre: nothing to take out
        with np.errstate(invalid="ignore", divide="ignore"):
            log_d = np.vstack([np.log(true), np.zeros((1, n))])
            factor = nominal / true
        sums = np.zeros((4, log_d.shape[0], n + 1))
        for k, term in enumerate((log_d, j[:-1] * log_d, j[:-1] ** 2 * log_d, log_d * log_d)):
            sums[k, :, 1:] = np.cumsum(term, axis=1)
        return LineSnapping(log_d, sums, factor, int(direction))


@nb.njit(cache=True, error_model="numpy", **INTERNAL)
def _run_residuals(bands, s, m, log_d, sums, out):
    """Per candidate (and, last, no snapping): the squared residual of the run's log
    spacings less the candidate's from a smooth trend (zeros for runs too short to
    tell).

    The trend is fitted on the orthogonal basis 1, t, t^2 - mean over the centred
    spacing index t; the residual is the sum of squares less the three projections,
    whose sums come from the run's own and the tables' running sums, so that each
    candidate costs one product per spacing.
    """
    out[:] = 0.0
    if m < 3:
        return
    quad = m >= 6
    c = 0.5 * (m - 1)
    st = 0.0
    for j in range(m):
        st += (j - c) * (j - c)
    sq = 0.0
    for j in range(m):
        sq += ((j - c) * (j - c) - st / m) ** 2
    ls = np.empty(m)
    l0 = 0.0
    l1 = 0.0
    l2 = 0.0
    l3 = 0.0
    for j in range(m):
        v = np.log(bands[s + j + 1, F_CENTRE] - bands[s + j, F_CENTRE])
        ls[j] = v
        l0 += v
        l1 += j * v
        l2 += j * j * v
        l3 += v * v
    for ph in range(out.shape[0]):
        cross = 0.0
        for j in range(m):
            cross += ls[j] * log_d[ph, j]
        y0 = l0 - sums[0, ph, m]
        y1 = l1 - sums[1, ph, m]
        y2 = l2 - sums[2, ph, m]
        yy = l3 - 2.0 * cross + sums[3, ph, m]
        yt = y1 - c * y0
        r = yy - y0 * y0 / m - yt * yt / st
        if quad:
            yq = (y2 - 2.0 * c * y1 + c * c * y0) - st / m * y0
            r -= yq * yq / sq
        out[ph] = max(r, 0.0) if np.isfinite(r) else IMPOSSIBLE


@nb.njit(cache=True, error_model="numpy", **INTERNAL)
def _runs(bands, count, starts, ends):
    """Runs of one row: consecutive bands with centres whose spacings change smoothly."""
    nr = 0
    q = 0
    while q < count:
        if not np.isfinite(bands[q, F_CENTRE]):
            q += 1
            continue
        s = q
        while q + 1 < count and np.isfinite(bands[q + 1, F_CENTRE]):
            d_new = bands[q + 1, F_CENTRE] - bands[q, F_CENTRE]
            if d_new <= 2.0:
                break
            if q > s:
                d_old = bands[q, F_CENTRE] - bands[q - 1, F_CENTRE]
                if not (1.0 / RUN_RATIO < d_new / d_old < RUN_RATIO):
                    break
            q += 1
        starts[nr] = s
        ends[nr] = q
        nr += 1
        q += 1
    return nr


def desnap_intervals(bands, counts, snapping: LineSnapping, nominal=None) -> int:
    """Take the column snapping out of every valid band's ``F_INTERVAL`` (in place).

    Parameters
    ----------
    bands, counts : numpy.ndarray
        One pattern's detector output (rows, bands, fields) and band counts.
    snapping : LineSnapping
        The pattern's tables (:meth:`LineSnapping.of`).
    nominal : numpy.ndarray, optional
        ``(rows, bands)`` output: where a run was corrected, each band's centre had the
        lines been at their nominal columns (from the run's first band on; only the
        differences along a run mean anything), else NaN.

    Returns
    -------
    int
        Runs whose intervals were corrected.
    """
    if bands.shape[1] > snapping.log_d.shape[1] + 1:
        raise ValueError(f"desnap_intervals: {bands.shape[1]} bands per row, tables for "
                         f"{snapping.log_d.shape[1] + 1}")  # fmt: skip
    if nominal is None:
        nominal = np.empty(bands.shape[:2])
    return _desnap(bands, counts, snapping.log_d, snapping.sums, snapping.factor,
                   snapping.direction, nominal)  # fmt: skip


@nb.njit(cache=True, error_model="numpy", nogil=True, **NO_CFUNC)
def _desnap(bands, counts, log_d, sums, factor, direction, nominal):
    """:func:`desnap_intervals` on the tables."""
    rows = counts.shape[0]
    width = bands.shape[1]
    cands = factor.shape[0]
    starts = np.empty((rows, width), np.int64)
    ends = np.empty((rows, width), np.int64)
    nruns = np.empty(rows, np.int64)
    run_of = np.empty((rows, width), np.int64)
    most = 1
    for r in range(rows):
        nominal[r, :] = np.nan
        nruns[r] = _runs(bands[r], counts[r], starts[r], ends[r])
        most = max(most, nruns[r])
    # rows hold a few runs: the residuals are sized by the most, not by the bands
    res = np.empty((rows, most, cands + 1))
    for r in range(rows):
        run_of[r, : counts[r]] = -1
        for i in range(nruns[r]):
            s = starts[r, i]
            e = ends[r, i]
            run_of[r, s : e + 1] = i
            _run_residuals(bands[r], s, e - s, log_d, sums, res[r, i])
    up = np.empty((rows, width), np.int64)  # link to the row below (r + 1)
    down = np.empty((rows, width), np.int64)  # link to the row above (r - 1)
    for r in range(rows - 1):
        nearest_partners(bands, counts, r, r + 1, LINK_REACH, up[r])
        nearest_partners(bands, counts, r + 1, r, LINK_REACH, down[r + 1])
    fixed = 0
    tot = np.empty(cands + 1)
    cur = np.empty(width, np.int64)
    nxt = np.empty(width, np.int64)
    seen = np.zeros(most, np.bool_)
    for r in range(rows):
        for i in range(nruns[r]):
            s = starts[r, i]
            e = ends[r, i]
            m = e - s
            if m < MIN_SPACINGS:
                continue
            tot[:] = res[r, i]
            for way in (1, -1):
                for j in range(m + 1):
                    cur[j] = s + j
                rr = r
                for _ in range(REACH_ROWS):
                    nr = rr + way
                    if nr < 0 or nr >= rows:
                        break
                    any_link = False
                    for j in range(m + 1):
                        q = cur[j]
                        nxt[j] = -1
                        if q >= 0:
                            nxt[j] = up[rr, q] if way == 1 else down[rr, q]
                            any_link = any_link or nxt[j] >= 0
                    if not any_link:
                        break
                    seen[: nruns[nr]] = False
                    for j in range(m + 1):
                        q = nxt[j]
                        if q < 0:
                            continue
                        ib = run_of[nr, q]
                        if ib < 0 or seen[ib]:
                            continue
                        seen[ib] = True
                        # line of the other run's first band, in bands from this run's
                        dn = j - (q - starts[nr, ib])
                        _pool(tot, res[nr, ib], dn * direction)
                    for j in range(m + 1):
                        cur[j] = nxt[j]
                    rr = nr
            best = 0
            for ph in range(1, cands):
                if tot[ph] < tot[best]:
                    best = ph
            if not tot[best] < MIN_GAIN * tot[cands]:
                continue
            fixed += 1
            _correct_run(bands[r], s, m, factor[best], nominal[r])
    return fixed


@nb.njit(cache=True, error_model="numpy", **NO_CFUNC)
def _pool(tot, other, shift):
    """Add another run's residuals, each under the candidate it has when this run has
    candidate ``c`` (its first line is line ``c + shift``)."""
    cands = tot.shape[0] - 1
    for c in range(cands):
        o = c + shift
        tot[c] += other[o] if 0 <= o < cands else IMPOSSIBLE
    tot[cands] += other[cands]


@nb.njit(cache=True, error_model="numpy", **INTERNAL)
def _correct_run(bands, s, m, factor, nominal):
    """Scale the run's intervals by their nominal spacings over the measured ones, and
    put the centres the lines would have at their nominal columns in ``nominal``."""
    sp = np.empty(m)
    ns = np.empty(m)
    nominal[s] = bands[s, F_CENTRE]
    for j in range(m):
        sp[j] = bands[s + j + 1, F_CENTRE] - bands[s + j, F_CENTRE]
        # the spacing had the lines been at their nominal centres
        ns[j] = sp[j] * factor[j]
        nominal[s + j + 1] = nominal[s + j] + ns[j]
    for j in range(m + 1):
        k = s + j
        # only valid bands measured alone whose interval is the detector's plain one:
        # the mean of their two spacings, or the linear extrapolation at a run's end
        # (not one taken from one side of a depth edge or a trend, nor a periodic
        # run's, which its sweep was read with)
        if bands[k, F_VALID] != BAND_VALID:
            continue
        if 0 < j < m:
            plain = 0.5 * (sp[j - 1] + sp[j])
            f = (ns[j - 1] + ns[j]) / (sp[j - 1] + sp[j])
        elif m >= 2:
            a1, a2 = (ns[0], ns[1]) if j == 0 else (ns[m - 1], ns[m - 2])
            b1, b2 = (sp[0], sp[1]) if j == 0 else (sp[m - 1], sp[m - 2])
            plain = 1.5 * b1 - 0.5 * b2
            f = (1.5 * a1 - 0.5 * a2) / plain
        else:
            continue
        if abs(bands[k, F_INTERVAL] - plain) <= 1e-9 * plain:
            bands[k, F_INTERVAL] *= f


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernels on a tiny run."""
    pattern = Pattern(channel="red", kind="uniform", width_px=3.0, pitch_px=20.4,
                      offset_px=0.0)  # fmt: skip
    snapping = LineSnapping.of(pattern, 400, 1, 12)
    bands = np.full((2, 12, N_FIELDS), np.nan)
    bands[:, :10, F_CENTRE] = 10.0 + 20.4 * np.arange(10)
    bands[:, :10, F_INTERVAL] = 20.4
    bands[:, :10, F_VALID] = BAND_VALID
    desnap_intervals(bands, np.array([10, 10]), snapping)
