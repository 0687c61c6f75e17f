"""The full-resolution depth from the analysis grid, and the lone cells dropped before it.

``upsample_grid`` interpolates over the cells that have a value: a pixel keeps one where
at least three quarters of its bilinear weight lies on them.  ``lone_cells`` names the
cells with a depth that fewer than 4 of their 8 neighbours share.
"""

import numpy as np
import pytest

from lightflow.app.core.causes import lone_cells
from lightflow.app.core.results import upsample_grid

STRIDE = 4


def _ramp(gh, gw):
    """A smooth grid (a plane in depth), so that bilinear values can be checked exactly."""
    y, x = np.mgrid[0:gh, 0:gw].astype(np.float32)
    return (0.8 + 0.001 * x + 0.002 * y).astype(np.float32)


def _ramp_pixels(h, w):
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    return 0.8 + 0.001 * ((x + 0.5) / STRIDE - 0.5) + 0.002 * ((y + 0.5) / STRIDE - 0.5)


def test_full_grid_is_plain_bilinear():
    grid = _ramp(30, 40)
    out = upsample_grid(grid, STRIDE, (160, 120))
    assert out.shape == (120, 160) and out.dtype == np.float32
    # pixel x sits at (x + 0.5) / 4 - 0.5 in cells: pixel 6 at 1.125
    assert out[6, 6] == pytest.approx(0.8 + 0.003 * 1.125, abs=1e-6)
    assert np.isfinite(out).all()


def test_one_cell_hole_costs_one_and_a_half_cells():
    grid = _ramp(30, 40)
    grid[10, 20] = np.nan
    out = upsample_grid(grid, STRIDE, (160, 120))
    missing = np.isnan(out)
    # its own 16 pixels and the 2 nearest of each neighbour's row or column beside it
    # (plain bilinear lost 8 x 8 = 64)
    assert np.count_nonzero(missing) == 16 + 4 * 2
    assert missing[40:44, 80:84].all()
    # the values around the hole: the valid cells' weighted mean, within one cell's rise
    # of the plane (0.003), and the plane's own where no weight fell on the hole
    ys, xs = np.nonzero(~missing[32:52, 72:92])
    cy = (ys + 32 + 0.5) / STRIDE - 0.5
    cx = (xs + 72 + 0.5) / STRIDE - 0.5
    want = 0.8 + 0.001 * cx + 0.002 * cy
    err = np.abs(out[32:52, 72:92][~missing[32:52, 72:92]] - want)
    assert err.max() < 0.003
    assert np.abs(out[2:30, 2:158] - _ramp_pixels(30, 160)[2:, 2:158]).max() < 1e-6


def test_edge_cells_reach_a_quarter_cell_past_their_centre():
    grid = np.full((30, 40), np.nan, np.float32)
    grid[:, :20] = 1.0  # the left half has a depth
    out = upsample_grid(grid, STRIDE, (160, 120))
    has = np.isfinite(out)
    # cell 19's centre is at x = 77.5: pixels 77 and 78 (within 1 px) keep the depth,
    # 79 (1.5 px: the weight 0.625) does not
    assert has[:, :79].all() and not has[:, 79:].any()
    assert np.all(out[has] == 1.0)


def test_lone_cell_and_thin_strip_keep_their_centre_pixels():
    grid = np.full((30, 40), np.nan, np.float32)
    grid[5, 5] = 1.0
    grid[20, 10:30] = 1.0  # a strip one row tall
    out = upsample_grid(grid, STRIDE, (160, 120))
    # a lone cell keeps the 2 x 2 pixels around its centre (weight 0.875**2), where plain
    # bilinear kept none: lone_cells drops such cells before
    assert np.nonzero(np.isfinite(out[0:40, 0:40]))[0].tolist() == [21, 21, 22, 22]
    # the strip keeps the two pixel rows nearest its centre line (weight 0.875)
    rows = np.nonzero(np.isfinite(out[:, 40:120]).any(axis=1))[0]
    assert rows.tolist() == [81, 82]


def test_size_not_a_multiple_of_the_stride_and_colour():
    grid = _ramp(31, 41)
    grid[10, 20] = np.nan
    out = upsample_grid(grid, STRIDE, (163, 125))
    assert out.shape == (125, 163)
    assert np.count_nonzero(np.isnan(out)) == 16 + 4 * 2
    colour = np.dstack([grid, grid, grid])
    out3 = upsample_grid(colour, STRIDE, (163, 125))
    assert out3.shape == (125, 163, 3)
    assert np.array_equal(np.isnan(out3[..., 1]), np.isnan(out), equal_nan=False)


def test_lone_cells():
    depth = np.full((20, 30), np.nan, np.float32)
    depth[2, 2] = 1.0  # alone: 0 neighbours
    depth[6, 5:15] = 1.0  # a strip one row tall: 2 neighbours each
    depth[10:12, 5:15] = 1.0  # two rows tall: 5 neighbours inside, 3 at its ends
    depth[14:20, 20:30] = 1.0  # a block at the border: 3 at its corner, 5 on its edges
    lone = lone_cells(depth)
    assert lone[2, 2] and lone[6, 5:15].all()
    assert not lone[10:12, 6:14].any()
    assert lone[10, 5] and lone[11, 14]  # the ends of the two-row strip: 3 neighbours
    # its corners have 3 (the border counts as no depth), its edges 5
    assert lone[14, 20] and lone[14, 29] and lone[19, 20] and lone[19, 29]
    assert not lone[14, 21:29].any() and not lone[15:19, 20].any()
    assert not lone[np.isnan(depth)].any()
