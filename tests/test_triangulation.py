"""Triangulated depth of bands whose lines both patterns agree on (app/core/triangulation.py).

Bands are placed exactly where the rig's lines light a known surface (each band's
centre is the camera column at which its line's projector column is met), so the
depth the module gives can be checked against the surface to a hundredth of a
millimetre.
"""

from pathlib import Path

import numpy as np
import pytest
from lit_surface import STRIDE, cell_x, refine, surface_bands, triangulation

from lightflow.app.core import triangulation as triangulation_module
from lightflow.app.core.bands import (
    BAND_PERIODIC,
    F_CENTRE,
    F_INTERVAL,
    F_LENGTH,
    F_VALID,
    N_FIELDS,
)
from lightflow.app.core.rig import load_rig

RIGS = Path(__file__).resolve().parents[1] / "app" / "rigs"


def setup(rig_name="two-projector.json", depth_of_x=lambda x: np.full(x.shape, 0.75)):
    rig = load_rig(RIGS / rig_name)
    tri, row_y, grid = triangulation(rig)
    bands, counts = surface_bands(rig, tri, row_y, depth_of_x)
    return rig, tri, bands, counts, grid


def cell_truth(grid, depth_of_x):
    return np.broadcast_to(depth_of_x(cell_x(grid)), grid)


@pytest.mark.parametrize("rig_name", ["two-projector.json", "two-projector-distorted.json",
                                      "single-projector.json"])  # fmt: skip
def test_a_board_is_triangulated_to_a_hundredth_of_a_millimetre(rig_name):
    """A plane at 0.75 m, the prior (the flows' depth) 2 % off: every cell between two
    bands of the board gets its depth within 0.01 mm, and a predicted error of about
    0.05 % of it."""
    rig, tri, bands, counts, grid = setup(rig_name)
    n, depth, std = refine(tri, bands, counts, grid, 0.765)
    have = np.isfinite(depth)
    print(f"\n{rig_name}: {n} cells, {have.mean():.1%} of the grid")
    assert have.mean() > 0.6
    assert np.max(np.abs(depth[have] - 0.75)) < 1e-5
    assert np.all((std[have] > 0.0) & (std[have] < 0.001))


def test_pulses_between_lines_are_triangulated_on_a_line():
    """One pattern's lines swept past their neighbours (L = 1.4 B): its bands are the
    pulses of a periodic run, half-way between two lines (an odd integer part of L /
    B).  They are read on the next line, and the board at 0.75 m keeps its depth
    within 0.01 mm (before: a held-out board before a wall took a pair of lines one
    beat off, 22 mm short)."""
    rig, tri, bands, counts, grid = setup()
    for r in range(counts.shape[1]):
        c = bands[1, r, : counts[1, r], F_CENTRE].copy()
        bands[1, r, :, F_CENTRE] = np.nan
        counts[1, r] = len(c) - 1
        pulses = bands[1, r, : len(c) - 1]
        pulses[:, F_CENTRE] = 0.5 * (c[:-1] + c[1:])
        pulses[:, F_INTERVAL] = np.diff(c)
        pulses[:, F_LENGTH] = 1.4 * np.diff(c)
        pulses[:, F_VALID] = BAND_PERIODIC
    n, depth, std = refine(tri, bands, counts, grid, 0.765)
    have = np.isfinite(depth)
    print(f"\n{n} cells, {have.mean():.1%} of the grid")
    assert have.mean() > 0.6
    assert np.max(np.abs(depth[have] - 0.75)) < 1e-5


def test_a_gap_in_a_lines_trace_takes_the_line_decided_above_and_below():
    """A board at 0.75 m, the second pattern's bands taken out on image rows 400-480 and
    from row 900 down: the first pattern's bands there have no pair of lines (nor a run
    to be carried on from).  On rows 400-480 their lines' traces are decided above and
    below, and they take those lines: the board's depth within 0.01 mm.  From row 900
    down only the rows above decide them, and they stay without.  (Measured: 99.8 % of
    the gap's cells, 0.0001 mm off; none below 900; before, none in the gap.)"""
    rig, tri, bands, counts, grid = setup()
    row_y = np.arange(grid[0]) * STRIDE + 1
    gap = (row_y >= 400) & (row_y < 480)
    below = row_y >= 900
    bands[1, gap | below, :, F_CENTRE] = np.nan
    n, depth, std = refine(tri, bands, counts, grid, 0.75)
    have = np.isfinite(depth)
    print(f"\ngap {have[gap].mean():.1%}, below {have[below].mean():.1%}")
    assert have[gap].mean() > 0.95 and np.all(np.abs(depth[gap][have[gap]] - 0.75) < 1e-5)
    assert not have[below].any() and have[~gap & ~below].all()


def test_the_other_patterns_depth_is_carried_on_along_a_circle():
    """:func:`_circle_depth`: through three points of a sphere, cut by the plane of one
    image row's rays (tilted: ray y 0.1), the depth on another ray of the row is the
    sphere's to 1e-9 m up to its limb, and none past it; three points of a plane (in
    line) give the plane's depth."""
    circle_depth = triangulation_module._circle_depth.py_func
    centre, radius, ry = np.array([0.02, 0.06, 0.8]), 0.1, 0.1

    def sphere(rx):  # the near crossing of the ray (rx, ry, 1) with the sphere, or NaN
        d = np.array([rx, ry, 1.0])
        b = d @ centre
        disc = b * b - (d @ d) * (centre @ centre - radius**2)
        return (b - np.sqrt(disc)) / (d @ d) if disc >= 0 else np.nan

    (ax, bx, cx), limb = (-0.03, 0.0, 0.04), 0.1492  # rx where the row's rays graze it
    args = (ax, sphere(ax), bx, sphere(bx), cx, sphere(cx), ry)
    for rx in (-0.05, 0.02, 0.1, 0.145):
        assert abs(circle_depth(*args, rx) - sphere(rx)) < 1e-9
    assert np.isnan(sphere(limb + 0.002)) and np.isnan(circle_depth(*args, limb + 0.002))

    def plane(rx):  # z = 0.7 + 0.2 x
        return 0.7 / (1.0 - 0.2 * rx)

    args = (ax, plane(ax), bx, plane(bx), cx, plane(cx), 0.0)
    assert abs(circle_depth(*args, 0.2) - plane(0.2)) < 1e-9


def test_the_other_patterns_depth_reaches_further_only_towards_a_limb(monkeypatch):
    """:func:`_other_depth` carries a run's circle on for one of its spacings, and up to
    ``FAR_REACH`` of them where the spacings change towards the band (a limb: 15 % here,
    three points of a sphere), flagged as far; on a board (equal spacings) no further
    than one."""
    for name in ("_ray_at", "_circle_depth"):  # kernels without a Python entry point
        monkeypatch.setattr(triangulation_module, name,
                            getattr(triangulation_module, name).py_func)  # fmt: skip
    other_depth = triangulation_module._other_depth.py_func
    width, f, c0 = 1600, 1000.0, 800.0
    rays = np.zeros((1, width, 2))
    rays[0, :, 0] = (np.arange(width) - c0) / f  # one image row, ray y 0
    centre, radius = np.array([0.02, 0.0, 0.8]), 0.1

    def sphere(rx):
        d = np.array([rx, 0.0, 1.0])
        b = d @ centre
        return (b - np.sqrt(b * b - (d @ d) * (centre @ centre - radius**2))) / (d @ d)

    def run(rxs, depth):
        """The first pattern's three decided bands at rays ``rxs`` (lines 10-12)."""
        bands = np.full((2, 1, 4, N_FIELDS), np.nan)
        bands[0, 0, :3, F_CENTRE] = c0 + f * np.asarray(rxs)
        counts = np.array([[3], [0]])
        line = np.full((2, 1, 4), -1, np.int64)
        line[0, 0, :3] = (10, 11, 12)
        z = np.full((2, 1, 4), np.nan)
        z[0, 0, :3] = [depth(rx) for rx in rxs]
        return lambda rx: other_depth(bands, counts, line, z, rays, 0, 0, c0 + f * rx, 1)

    # the sphere's limb lies at ray x 0.1514; surface points 0.2 rad apart, up to 0.7 rad
    th = np.array([0.3, 0.5, 0.7])
    rxs = (centre[0] + radius * np.sin(th)) / (centre[2] - radius * np.cos(th))
    s = rxs[2] - rxs[1]  # 15 % shorter than the spacing before
    ball = run(rxs, sphere)
    for k, far in ((0.5, False), (1.5, True)):
        w, flag = ball(rxs[2] + k * s)
        assert flag == far and abs(w - sphere(rxs[2] + k * s)) < 1e-9
    assert np.isnan(ball(rxs[2] + 2.2 * s)[0])  # past FAR_REACH (and the limb)
    board = run([0.0, 0.03, 0.06], lambda rx: 0.75)
    w, flag = board(0.06 + 0.8 * 0.03)
    assert not flag and abs(w - 0.75) < 1e-9
    assert np.isnan(board(0.06 + 1.5 * 0.03)[0])


def test_a_tilted_board_with_a_prior_two_lines_off():
    """Depth rising 0.65 -> 0.85 m across the image, the prior 8 % long everywhere (more
    than a line of either pattern): the lines are still found, or left alone, never
    wrong."""
    def slope(x):
        return 0.65 + 0.2 * x / 1600.0

    rig, tri, bands, counts, grid = setup(depth_of_x=slope)
    truth = cell_truth(grid, slope)
    prior = truth * 1.08
    depth = np.full(grid, np.nan, np.float32)
    std = np.full(grid, np.nan, np.float32)
    tri.refine(bands, counts, 1, STRIDE, prior, np.ones(grid, bool), depth, std)
    have = np.isfinite(depth)
    print(f"\ncells with depth: {have.mean():.1%}")
    assert have.mean() > 0.5
    # linear between bands: a plane's depth along a row is not quite linear in x
    assert np.max(np.abs(depth[have] - truth[have])) < 2e-4


def test_no_prior_and_no_motion_give_no_depth():
    rig, tri, bands, counts, grid = setup()
    n, depth, _ = refine(tri, bands, counts, grid, np.nan)
    assert n == 0 and not np.isfinite(depth).any()
    n, depth, _ = refine(tri, bands, counts, grid, 0.75, moving=np.zeros(grid, bool))
    assert n == 0 and not np.isfinite(depth).any()


def test_a_prior_far_off_names_no_wrong_line():
    """The prior at 1.2 m for a board at 0.75 m: no pair of lines within reach of the
    prior agrees, so nothing is written."""
    rig, tri, bands, counts, grid = setup()
    n, depth, _ = refine(tri, bands, counts, grid, 1.2)
    have = np.isfinite(depth)
    assert np.all(np.abs(depth[have] - 0.75) < 1e-4)
    assert have.mean() < 0.01


def test_no_depth_is_interpolated_across_a_step():
    """Left half at 0.70 m, right half at 0.90 m: each side triangulated, and no cell
    between them gets a depth in between."""
    def step(x):
        return np.where(x < 800, 0.70, 0.90)

    rig, tri, bands, counts, grid = setup(depth_of_x=step)
    truth = cell_truth(grid, step)
    prior = truth.astype(np.float32)
    depth = np.full(grid, np.nan, np.float32)
    std = np.full(grid, np.nan, np.float32)
    tri.refine(bands, counts, 1, STRIDE, prior, np.ones(grid, bool), depth, std)
    have = np.isfinite(depth)
    assert have[:, : grid[1] // 2 - 20].mean() > 0.6 and have[:, grid[1] // 2 + 20 :].mean() > 0.6
    off = np.minimum(np.abs(depth[have] - 0.70), np.abs(depth[have] - 0.90))
    assert np.max(off) < 1e-4


def test_depth_reaches_past_the_moving_cells_on_their_surface_only():
    """Left half at 0.70 m, right half at 0.90 m, the lines found moving in a block of
    the left half only (a ball whose limb shows no sweep): the bands linked to the block
    through bands of its surface carry its depth a few lines further, never across the
    step to the other surface, and not at all where the lines were seen standing still."""
    def step(x):
        return np.where(x < 800, 0.70, 0.90)

    rig, tri, bands, counts, grid = setup(depth_of_x=step)
    prior = cell_truth(grid, step).astype(np.float32)
    moving = np.zeros(grid, bool)
    moving[:, 100:150] = True  # x 400-600
    x = cell_x(grid)

    def depth_with(still):
        depth = np.full(grid, np.nan, np.float32)
        std = np.full(grid, np.nan, np.float32)
        tri.refine(bands, counts, 1, STRIDE, prior, moving, depth, std, still=still)
        return depth

    depth = depth_with(None)
    have = np.isfinite(depth)
    beyond = have & ~moving
    reach = x[beyond.any(axis=0)]
    print(f"\ndepth beyond the block: x {reach.min():.0f}-{reach.max():.0f}")
    assert np.all(np.abs(depth[have] - 0.70) < 1e-4)
    # the lines of either pattern on both sides of the block, up to the step
    assert have[:, 150:160].mean() > 0.9 and have[:, 90:100].mean() > 0.9
    assert not have[:, x > 810].any()
    # lines seen standing still outside the block: its depth ends at its last bands
    depth = depth_with(~moving)
    beyond = np.isfinite(depth) & ~moving
    assert not beyond[:, (x < 380) | (x > 620)].any()


def test_runs_are_carried_on_to_a_limb_with_no_flow():
    """A cylinder bulging from 0.80 to 0.70 m (its limb at x 200 and 1400) before a wall
    at 1.1 m, the flows' depth known only on its middle (x 600-1000), one pattern's runs
    broken at x 1040: the runs are carried on band by band, where the other pattern
    agrees, to bands the flow never reached, with their exact depths; never onto the
    wall."""
    def bulge(x):
        u = np.clip((x - 800.0) / 600.0, -1.0, 1.0)
        return np.where(np.abs(x - 800.0) < 600.0, 0.80 - 0.1 * np.sqrt(1.0 - u * u), 1.1)

    rig, tri, bands, counts, grid = setup(depth_of_x=bulge)
    # pattern 1's runs end at x 1040 (a faint band): its lines beyond are named by no flow
    centre = bands[1, :, :, F_CENTRE]
    first = np.argmax(centre > 1040.0, axis=1)
    centre[np.arange(len(first)), first] = np.nan
    truth = cell_truth(grid, bulge)
    x = cell_x(grid)
    prior = np.where(np.abs(x - 800.0) < 200.0, truth, np.nan).astype(np.float32)
    depth = np.full(grid, np.nan, np.float32)
    std = np.full(grid, np.nan, np.float32)
    tri.refine(bands, counts, 1, STRIDE, prior, np.ones(grid, bool), depth, std)
    have = np.isfinite(depth)
    left = (x > 460.0) & (x < 540.0)  # both patterns' runs reach here from the middle
    right = (x > 1030.0) & (x < 1070.0)  # pattern 0's run, carried past pattern 1's end
    print(f"\ncells with depth: x 460-540 {have[:, left].mean():.1%}, "
          f"x 1030-1070 {have[:, right].mean():.1%}; "
          f"reach x {x[have.any(axis=0)].min():.0f}-{x[have.any(axis=0)].max():.0f}")
    assert have[:, left].mean() > 0.9 and have[:, right].mean() > 0.8
    # the other pattern's depth is carried on along its circle, so the runs reach the
    # limb (measured: 80 % of the cells at x 200-260, to x 213; with a parabola through
    # three bands, 33 %)
    assert have[:, (x > 200.0) & (x < 260.0)].mean() > 0.7
    # linear between bands on a curved surface: within a millimetre, and within
    # 2.5 mm in the last 60 px before the limb, where it bends fastest (measured:
    # median 0.03 mm, max 0.96 mm; 2.34 mm before the limb)
    err = np.abs(depth - truth)
    limb = have & (x < 260.0)
    print(f"error: median {np.median(err[have]) * 1e3:.3f} mm, "
          f"max {err[have & ~limb].max() * 1e3:.2f} mm, {err[limb].max() * 1e3:.2f} mm "
          "before the limb")
    assert np.median(err[have]) < 1e-4 and np.max(err[have & ~limb]) < 1.5e-3
    assert np.max(err[limb]) < 2.5e-3
    assert not have[:, np.abs(x - 800.0) > 600.0].any()


def round_surface(cam):
    """A vertical cylinder of radius 0.1 m, its axis 0.85 m away on the camera's optical
    axis, before a wall at 1.1 m: depth of image column x (``cam``: an undistorted
    camera; the rays of a column graze it, at its limb, or miss it)."""

    def depth(x):
        rx = (np.asarray(x, np.float64) - cam.K[0, 2]) / cam.K[0, 0]
        # (rx t)^2 + (t - 0.85)^2 = 0.1^2, the near root
        a, b, c = rx * rx + 1.0, -2.0 * 0.85, 0.85**2 - 0.1**2
        disc = b * b - 4.0 * a * c
        near = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2.0 * a)
        return np.where(disc > 0.0, near, 1.1)

    return depth


def test_the_cells_past_the_last_band_reach_the_limb_on_the_circle():
    """A cylinder whose bands near its left limb are too faint to see (none of either
    pattern within 30 px of it), the flows' depth and the moving cells only on its middle:
    the cells between its last bands and the limb take the depth of the circle through
    the last three bands of a run (:func:`_limb_depth`), and none lies past the limb.
    (Measured: all the cells of the 30 px ring, 1.85 mm off at most, where the surface
    turns away fastest; none past the limb.  Without the limb's circle: none of the
    ring, the cells reaching x 626 of the limb's 590.)"""
    rig, tri, bands, counts, grid = setup()
    surface = round_surface(rig.camera)
    bands, counts = surface_bands(rig, tri, tri.row_y, surface)
    x = cell_x(grid)
    limb = x[np.argmax(surface(x) < 1.0)]  # the first column on the cylinder
    centre = bands[:, :, :, F_CENTRE]
    centre[centre < limb + 30.0] = np.nan
    truth = cell_truth(grid, surface)
    middle = np.abs(surface(x) - 0.75) < 0.01
    prior = np.where(middle, truth, np.nan).astype(np.float32)
    depth = np.full(grid, np.nan, np.float32)
    std = np.full(grid, np.nan, np.float32)
    moving = np.broadcast_to(middle, grid).copy()
    tri.refine(bands, counts, 1, STRIDE, prior, moving, depth, std)
    have = np.isfinite(depth)
    ring = (x > limb) & (x < limb + 30.0)
    err = np.abs(depth - truth)
    print(f"\nlimb x {limb:.0f}, reach x {x[have.any(axis=0)].min():.0f}; ring: "
          f"{have[:, ring].mean():.1%} of the cells, "
          f"max {err[:, ring][have[:, ring]].max() * 1e3 if have[:, ring].any() else 0:.2f} mm; "
          f"past the limb: {have[:, x < limb].sum()} cells")
    assert have[:, ring].mean() > 0.9
    assert err[:, ring][have[:, ring]].max() < 2.5e-3
    assert not have[:, x < limb].any()


def test_no_depth_is_carried_across_a_wall_between_two_blades():
    """Two blades at 0.70 m (columns below 600 and from 700 on), a wall at 1.1 m between
    them whose first pattern's lines are too faint to be found; the second pattern's wall
    bands get no line (the prior names the blades').  The blades' cells are the moving
    ones.  No wall cell gets a depth: at the blades' depth, a wall band's projector column
    lies between two lines.  Before, the blades' depth filled the wall between their
    edge bands, whose spacing the missing lines made look long (a fan's two blades at one
    depth, development rig 47: 3.4 % of its depth off the blades).  Each blade keeps its
    depth."""
    def scene(x):
        return np.where((x < 600.0) | (x >= 700.0), 0.70, 1.1)

    rig, tri, bands, counts, grid = setup(depth_of_x=scene)
    wall = (bands[..., F_CENTRE] > 600.0) & (bands[..., F_CENTRE] < 700.0)
    assert wall[0].any() and wall[1].any()
    for r in range(counts.shape[1]):  # the first pattern's wall bands: too faint
        keep = bands[0, r, ~wall[0, r]]
        bands[0, r] = np.nan
        bands[0, r, : len(keep)] = keep
        counts[0, r] -= wall[0, r].sum()
    x = cell_x(grid)
    moving = np.broadcast_to((x < 600.0) | (x >= 700.0), grid)
    n, depth, _ = refine(tri, bands, counts, grid, 0.70, moving=moving.copy())
    gap = (x > 612.0) & (x < 688.0)
    blades = moving & np.isfinite(depth)
    print(f"\nwall cells with depth: {np.isfinite(depth[:, gap]).mean():.1%}, blade cells: "
          f"{blades.sum() / moving.sum():.1%}")
    assert not np.isfinite(depth[:, gap]).any()
    assert blades.sum() > 0.9 * moving.sum()
    assert np.max(np.abs(depth[blades] - 0.70)) < 1e-4
