"""Line intervals from the arc through three lines, on exactly projected spheres and planes."""

from __future__ import annotations

import numpy as np
import pytest

from lightflow.app.core.arcs import MIN_CHANGE, ArcIntervals
from lightflow.app.core.bands import (
    BAND_LIMB,
    BAND_STEEP,
    BAND_VALID,
    F_CENTRE,
    F_INTERVAL,
    F_LENGTH,
    F_RAMP,
    F_VALID,
    N_FIELDS,
)
from lightflow.app.core.geometry import project_to_projector, undistort_pixels
from lightflow.app.core.rig import resolve_rig

STRIDE = 4
#: the middle of the measured rows, whose truths the tests compare with
M = 1
ITOL = 0.25


@pytest.fixture(scope="module")
def rig():
    return resolve_rig("two-projector")


def _surface_depth(rig, y, xs, surface):
    """Depth along camera row ``y`` at columns ``xs`` of a sphere ``(centre, radius)``
    or a plane ``(point, normal)``; NaN where the ray misses."""
    cam = rig.camera
    xy = undistort_pixels(cam.K, cam.dist, np.stack([xs, np.full_like(xs, y)], axis=-1))
    rays = np.column_stack([xy, np.ones(len(xs))])
    kind, a, b = surface
    a = np.asarray(a, float)
    if kind == "sphere":
        rc = rays @ a
        rr = (rays * rays).sum(1)
        disc = rc * rc - rr * (a @ a - b * b)
        z = (rc - np.sqrt(np.where(disc >= 0, disc, np.nan))) / rr
    else:
        n = np.asarray(b, float)
        z = (a @ n) / (rays @ n)
    return z, rays


def _row(rig, p, y, surface, lo, hi):
    """Line centres of pattern ``p`` along row ``y`` and the true interval at each."""
    proj, pat = rig.patterns[p]
    xs = np.arange(lo, hi, 0.01)
    z, rays = _surface_depth(rig, y, xs, surface)
    u = project_to_projector(proj, rays * z[:, None])[:, 0]
    ok = np.isfinite(u)
    xs, u = xs[ok], u[ok]
    k0 = np.ceil((u.min() - pat.offset_px) / pat.pitch_px)
    k1 = np.floor((u.max() - pat.offset_px) / pat.pitch_px)
    lines = pat.offset_px + pat.pitch_px * np.arange(k0, k1 + 1)
    order = np.argsort(u)
    centres = np.sort(np.interp(lines, u[order], xs[order]))
    du = np.gradient(u, xs)
    truth = pat.pitch_px / np.abs(np.interp(centres, xs, du))
    return centres, truth


def _bands(rig, y, surface, lo, hi, limb_ends=False, rows=3):
    """Detector-like output of ``rows`` measured rows ``STRIDE`` apart, centred on ``y``:
    both patterns' bands at their line centres with the mean spacing as interval; the
    true intervals and a depth grid row per measured row.  Returned for the middle row:
    its bands are ``bands[:, rows // 2]``."""
    ys = y + STRIDE * (np.arange(rows) - rows // 2)
    bands = np.full((2, rows, 64, N_FIELDS), np.nan)
    counts = np.zeros((2, rows), np.int64)
    truths = []
    for q, yq in enumerate(ys):
        for p in range(2):
            c, t = _row(rig, p, yq, surface, lo, hi)
            n = len(c)
            counts[p, q] = n
            bands[p, q, :n, F_CENTRE] = c
            bands[p, q, :n, F_VALID] = BAND_VALID
            bands[p, q, :n, F_LENGTH] = 4.0
            bands[p, q, :n, F_RAMP] = 0.8
            bands[p, q, 1:n - 1, F_INTERVAL] = 0.5 * (c[2:] - c[:-2])
            bands[p, q, [0, n - 1], F_VALID] = BAND_LIMB if limb_ends else -2.0
            if q == rows // 2:
                truths.append(t)
    gw = rig.camera.width // STRIDE
    cols = np.arange(gw) * STRIDE + 0.5 * (STRIDE - 1)
    depth = np.stack([_surface_depth(rig, yq, cols, surface)[0] for yq in ys])
    return bands, counts, truths, depth, ys.astype(np.int64)


def _none(bands):
    """No nominal centres (no snapping knows the lines)."""
    return np.full(bands.shape[:3], np.nan)


BALL = ("sphere", (0.03, 0.01, 0.75), 0.15)


def test_arc_intervals_are_the_tangent_on_a_sphere_where_the_mean_spacing_is_a_secant(rig):
    y = 620.0
    bands, counts, truths, depth, ys = _bands(rig, y, BALL, 300.0, 1300.0)
    before = bands[:, :, :, F_INTERVAL].copy()
    arcs = ArcIntervals(rig, ys)
    changed, rescued, _ = arcs.correct(bands, counts, _none(bands), depth, 1, STRIDE, ITOL)
    assert rescued == 0 and changed >= 10
    for p in range(2):
        n = counts[p, M]
        arc = bands[p, M, 1:n - 1, F_INTERVAL]
        done = arc != before[p, M, 1:n - 1]
        secant = before[p, M, 1:n - 1] / truths[p][1:-1] - 1
        err = arc / truths[p][1:-1] - 1
        # the secant is off by up to a per cent towards the limb; the arc within 0.02 %
        assert np.abs(secant[done]).max() > 0.008
        assert np.abs(err[done]).max() < 2e-4, (p, err)
        # the others: the secant within MIN_CHANGE (and the arc's precision), or spacings
        # that differ beyond the tolerance (next to the limb)
        d = np.diff(bands[p, M, :n, F_CENTRE])
        smooth = np.abs(d[1:] - d[:-1]) <= ITOL * 0.5 * (d[1:] + d[:-1])
        assert np.abs(err[~done & smooth]).max() < MIN_CHANGE + 2e-4


def test_arc_intervals_hold_with_a_depth_two_per_cent_off_and_on_a_tilted_plane(rig):
    y = 600.0
    bands, counts, truths, depth, ys = _bands(rig, y, BALL, 300.0, 1300.0)
    arcs = ArcIntervals(rig, ys)
    arcs.correct(bands, counts, _none(bands), depth * 1.02, 1, STRIDE, ITOL)
    for p in range(2):
        n = counts[p, M]
        err = bands[p, M, 1:n - 1, F_INTERVAL] / truths[p][1:-1] - 1
        err = err[np.abs(err) < 0.005]  # those it corrected (the others keep the secant)
        assert len(err) >= 0.7 * (n - 2)
        assert np.median(np.abs(err)) < MIN_CHANGE and np.abs(err).max() < 2e-3, (p, err)
    # a plane's secant is within MIN_CHANGE of its tangent: no band is read again
    plane = ("plane", (0.0, 0.0, 0.9), (0.35, 0.1, -1.0))
    bands, counts, truths, depth, ys = _bands(rig, y, plane, 100.0, 1500.0)
    assert arcs.correct(bands, counts, _none(bands), depth, 1, STRIDE, ITOL)[:2] == (0, 0)
    for p in range(2):
        n = counts[p, M]
        err = bands[p, M, 1:n - 1, F_INTERVAL] / truths[p][1:-1] - 1
        assert np.abs(err).max() < MIN_CHANGE, (p, err)


def test_a_limb_band_becomes_valid_with_the_arc_through_its_next_two_lines(rig):
    y = 620.0
    bands, counts, truths, depth, ys = _bands(rig, y, BALL, 300.0, 1300.0, limb_ends=True)
    # the limb bands' own cells have no depth yet: the nearest towards the run has
    for p in range(2):
        for end in (0, counts[p, M] - 1):
            j = int(round((bands[p, M, end, F_CENTRE] - 1.5) / STRIDE))
            depth[0, j - 1: j + 2] = np.nan
    arcs = ArcIntervals(rig, ys)
    changed, rescued, _ = arcs.correct(bands, counts, _none(bands), depth, 1, STRIDE, ITOL)
    # two of the four are where the lines spread out towards the limb (the side facing
    # its projector), by more than LIMB_CHANGE from one line to the next: limb bands still
    assert rescued >= 2 * len(ys)  # one more in a row whose limb line falls just so
    assert sum(bands[p, M, e, F_VALID] == BAND_VALID for p in range(2)
               for e in (0, counts[p, M] - 1)) == 2  # fmt: skip
    for p in range(2):
        for end in (0, counts[p, M] - 1):
            if bands[p, M, end, F_VALID] == BAND_LIMB:
                continue
            assert bands[p, M, end, F_VALID] == BAND_VALID
            # placed at a cell nearer the run (its own has no depth): within 0.5 %
            assert bands[p, M, end, F_INTERVAL] == pytest.approx(truths[p][end], rel=5e-3)
        # where they bunch (the side away from the projector) the band is rescued
        near = 0 if truths[p][0] < truths[p][-1] else counts[p, M] - 1
        assert bands[p, M, near, F_VALID] == BAND_VALID


def test_no_arc_without_a_depth_or_across_a_step_of_the_spacing(rig):
    y = 620.0
    bands, counts, truths, depth, ys = _bands(rig, y, BALL, 300.0, 1300.0)
    before = bands.copy()
    arcs = ArcIntervals(rig, ys)
    no_depth = np.full_like(depth, np.nan)
    assert arcs.correct(bands, counts, _none(bands), no_depth, 1, STRIDE, ITOL)[:2] == (0, 0)
    np.testing.assert_array_equal(bands, before)
    # a band whose two spacings differ beyond the tolerance (a depth edge) keeps its interval
    p, k = 1, 3
    bands[p, M, k + 1, F_CENTRE] += 0.4 * (bands[p, M, k + 1, F_CENTRE] - bands[p, M, k, F_CENTRE])
    kept = bands[p, M, k, F_INTERVAL]
    arcs.correct(bands, counts, _none(bands), depth, 1, STRIDE, ITOL)
    assert bands[p, M, k, F_INTERVAL] == kept


def _wall_beside(rig, y, surface, edge_x, wall_z):
    """Bands of ``surface`` left of camera column ``edge_x`` and of a fronto-parallel wall
    at ``wall_z`` right of it, the two bands at the edge of each pattern steep; the
    depth grid of both, and per pattern the index of the last band on ``surface``."""
    bl, cl, _, dl, ys = _bands(rig, y, surface, 300.0, edge_x)
    bw, cw, _, dw, _ = _bands(rig, y, ("plane", (0.0, 0.0, wall_z), (0.0, 0.0, -1.0)),
                              edge_x, 1500.0)  # fmt: skip
    bands = np.full_like(bl, np.nan)
    counts = cl + cw
    for p in range(2):
        for q in range(bl.shape[1]):
            n1, n = cl[p, q], counts[p, q]
            bands[p, q, :n1] = bl[p, q, :n1]
            bands[p, q, n1:n] = bw[p, q, :cw[p, q]]
            c = bands[p, q, :n, F_CENTRE]
            bands[p, q, :n, F_VALID] = BAND_VALID
            bands[p, q, 1:n - 1, F_INTERVAL] = 0.5 * (c[2:] - c[:-2])
            bands[p, q, [n1 - 1, n1], F_VALID] = BAND_STEEP
    return bands, counts, np.where(np.isfinite(dl), dl, dw), ys, cl[:, M] - 1


def test_a_steep_band_takes_its_arc_on_one_smooth_surface_not_beside_a_depth_edge(rig):
    """Bands whose two spacings differ too much for their mean (``BAND_STEEP``) become
    valid with the arc through their neighbours, at a depth from a cell near them (their
    own have none): on a sphere within 0.02 % of the tangent.  Beside a depth edge (the
    ball before a wall, a neighbour on each) the arcs through the next two lines on each
    side disagree with it, and the band stays without an interval, as it does where
    either side lacks a second line."""
    for y in (450.0, 620.0, 800.0):
        bands, counts, truths, depth, ys = _bands(rig, y, BALL, 300.0, 1300.0)
        for p in range(2):
            for q in range(len(ys)):
                bands[p, q, 1:counts[p, q] - 1, F_VALID] = BAND_STEEP
                for c in bands[p, q, 1:counts[p, q] - 1, F_CENTRE]:
                    depth[q, int(round((c - 1.5) / STRIDE))] = np.nan
        arcs = ArcIntervals(rig, ys)
        changed, rescued, _ = arcs.correct(bands, counts, _none(bands), depth, 1, STRIDE, ITOL)
        assert changed == 0
        for p in range(2):
            n = counts[p, M]
            valid = bands[p, M, 1:n - 1, F_VALID] == BAND_VALID
            # all but the two beside the run's ends, which lack a second line on one side
            np.testing.assert_array_equal(valid, np.arange(1, n - 1) % (n - 3) != 1)
            err = bands[p, M, 1:n - 1, F_INTERVAL][valid] / truths[p][1:-1][valid] - 1
            assert np.abs(err).max() < 2e-4, (y, p, err)
    for wall_z in (0.8, 0.9, 1.1):
        for edge_x in (700.0, 850.0, 1000.0):
            bands, counts, depth, ys, last = _wall_beside(rig, 620.0, BALL, edge_x, wall_z)
            arcs = ArcIntervals(rig, ys)
            assert arcs.correct(bands, counts, _none(bands), depth, 1, STRIDE, ITOL)[1] == 0
            for p in range(2):
                assert bands[p, M, last[p], F_VALID] == BAND_STEEP
                assert bands[p, M, last[p] + 1, F_VALID] == BAND_STEEP


def test_a_band_without_a_depth_of_its_own_takes_the_nearest_cells(rig):
    """The first pass may have no depth in a band's own cell (its flow was screened out):
    the nearest cell within DEPTH_REACH, in any direction, places the arc."""
    y = 620.0
    bands, counts, truths, depth, ys = _bands(rig, y, BALL, 300.0, 1300.0)
    # the middle measured row has no depth at all; the rows above and below have
    depth[M] = np.nan
    arcs = ArcIntervals(rig, ys)
    arcs.correct(bands, counts, _none(bands), depth, 1, STRIDE, ITOL)
    for p in range(2):
        n = counts[p, M]
        err = bands[p, M, 1:n - 1, F_INTERVAL] / truths[p][1:-1] - 1
        err = err[np.abs(err) < 0.005]  # those it corrected (the others keep the secant)
        assert len(err) >= 0.7 * (n - 2)
        assert np.abs(err).max() < 2e-3, (p, err)
    # beyond DEPTH_REACH nothing
    far = np.full_like(depth, np.nan)
    assert arcs.correct(bands, counts, _none(bands), far, 1, STRIDE, ITOL)[:2] == (0, 0)


def test_a_limb_band_placed_at_a_depth_the_frame_does_not_measure_is_placed_again(rig):
    """A limb band has no depth of its own: its arc is placed at the nearest cell's, which
    near a limb can be far off (other limb bands' flows).  Where the depth then measured at
    the band's own cell disagrees by more than RECHECK, ``recheck`` puts it there, and the
    arcs placed again give the band its true interval."""
    y = 620.0
    bands, counts, truths, depth, ys = _bands(rig, y, BALL, 300.0, 1300.0, limb_ends=True)
    ends = [(p, e) for p in range(2) for e in (0, counts[p, M] - 1)]
    first = depth * 1.4  # the first pass's depth around the run, 40 % far
    for p, e in ends:
        j = int(round((bands[p, M, e, F_CENTRE] - 1.5) / STRIDE))
        first[:, j - 1: j + 2] = np.nan
    arcs = ArcIntervals(rig, ys)
    before = bands.copy()
    arcs.correct(bands, counts, _none(bands), first, 1, STRIDE, ITOL)
    rescued = [(p, e) for p, e in ends if bands[p, M, e, F_VALID] == BAND_VALID]
    assert rescued
    off = [bands[p, M, e, F_INTERVAL] / truths[p][e] - 1 for p, e in rescued]
    assert max(np.abs(off)) > 0.03, off  # placed 40 % far: several per cent long
    # the frame then measures its depth at the bands' cells (here: the truth)
    again = arcs.recheck(before, bands, counts, first, depth, 1, STRIDE)
    assert again is not None
    second = before.copy()
    arcs.correct(second, counts, _none(second), again, 1, STRIDE, ITOL)
    for p, e in rescued:
        assert second[p, M, e, F_VALID] == BAND_VALID
        assert second[p, M, e, F_INTERVAL] == pytest.approx(truths[p][e], rel=5e-3)
    # where the depth measured agrees with the one the arcs were placed at: nothing to redo
    assert arcs.recheck(before, second, counts, again, again, 1, STRIDE) is None


def test_snapped_neighbours_take_their_nominal_centres(rig):
    """Lines on whole projector columns move each centre by up to half a column: the arc
    through them bends with it.  Where snapping knows the run's lines, the arc goes
    through the centres the lines would have at their nominal columns."""
    y = 620.0
    bands, counts, truths, depth, ys = _bands(rig, y, BALL, 300.0, 1300.0)
    nominal = np.full(bands.shape[:3], np.nan)
    rng = np.random.default_rng(3)
    for p in range(2):
        for q in range(len(ys)):
            n = counts[p, q]
            nominal[p, q, :n] = bands[p, q, :n, F_CENTRE]
            # a whole-column step: up to 0.3 camera px, the same line in every row
            if q == 0:
                jitter = rng.uniform(-0.3, 0.3, n)
            bands[p, q, :n, F_CENTRE] += jitter
            c = bands[p, q, :n, F_CENTRE]
            # the detector's intervals, with snapping's correction to the nominal spacing
            bands[p, q, 1:n - 1, F_INTERVAL] = 0.5 * (nominal[p, q, 2:n] - nominal[p, q, :n - 2])
            assert np.abs(np.diff(c) / np.diff(nominal[p, q, :n]) - 1).max() > 0.005
    arcs = ArcIntervals(rig, ys)
    blind = bands.copy()
    arcs.correct(blind, counts, _none(bands), depth, 1, STRIDE, ITOL)
    arcs.correct(bands, counts, nominal, depth, 1, STRIDE, ITOL)
    for p in range(2):
        n = counts[p, M]
        err = bands[p, M, 1:n - 1, F_INTERVAL] / truths[p][1:-1] - 1
        off = blind[p, M, 1:n - 1, F_INTERVAL] / truths[p][1:-1] - 1
        d = np.diff(nominal[p, M, :n])
        smooth = np.abs(d[1:] - d[:-1]) <= ITOL * 0.5 * (d[1:] + d[:-1])
        assert np.abs(err[smooth]).max() < MIN_CHANGE + 5e-4, (p, err)
        assert np.abs(off[smooth]).max() > 2 * np.abs(err[smooth]).max()


def test_the_option_turns_the_arcs_off(rig):
    import argparse

    from lightflow.app.core.pipeline import DepthPipeline, PipelineConfig
    from lightflow.app.options import add_pipeline_options, pipeline_config

    parser = argparse.ArgumentParser()
    add_pipeline_options(parser)
    assert pipeline_config(parser.parse_args([])).arc_intervals
    off = pipeline_config(parser.parse_args(["--arc-intervals", "off"]))
    assert not off.arc_intervals
    # placing the arcs again (ArcIntervals.recheck) is an option, off by default
    assert not pipeline_config(parser.parse_args([])).arc_recheck
    assert pipeline_config(parser.parse_args(["--arc-recheck", "on"])).arc_recheck
    assert DepthPipeline(rig, PipelineConfig(arc_intervals=False))._arcs is None
    assert DepthPipeline(rig, PipelineConfig())._arcs is not None
