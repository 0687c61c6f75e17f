"""Band centres exactly where a rig's lines light a known surface: the triangulation
tests' input (no detector, no image)."""

import numpy as np

from lightflow.app.core.bands import F_CENTRE, N_FIELDS
from lightflow.app.core.depth_model import DepthRange
from lightflow.app.core.geometry import project_to_projector
from lightflow.app.core.triangulation import LineTriangulation

STRIDE = 4


def surface_bands(rig, tri, row_y, depth_of_x, max_bands=64):
    """Per pattern and measured row, the centres of the bands its lines make on the
    surface ``depth_of_x(x)`` (depth per camera column, m; NaN: nothing there)."""
    width = rig.camera.width
    xs = np.arange(width, dtype=np.float64)
    bands = np.full((2, len(row_y), max_bands, N_FIELDS), np.nan)
    counts = np.zeros((2, len(row_y)), np.int64)
    z = depth_of_x(xs)
    for p, (proj, _) in enumerate(rig.patterns):
        lit = tri.lit[p, : tri.n_lit[p]]
        for r in range(len(row_y)):
            ray = tri.rays[r]
            pts = np.column_stack([ray * z[:, None], z])
            u = project_to_projector(proj, pts)[:, 0]
            # each line's crossing, within one surface piece (no crossing over a step)
            cross = []
            for k in range(len(lit)):
                d = u - lit[k]
                s = np.nonzero((d[:-1] <= 0) & (d[1:] > 0) & (np.abs(np.diff(z)) < 1e-3))[0]
                for j in s:
                    cross.append(j + d[j] / (d[j] - d[j + 1]))
            cross = np.sort(cross)[:max_bands]
            bands[p, r, : len(cross), F_CENTRE] = cross
            counts[p, r] = len(cross)
    return bands, counts


def triangulation(rig):
    """The rig's :class:`LineTriangulation` on every ``STRIDE``-th row: ``(tri, row_y,
    grid shape)``."""
    gh = rig.camera.height // STRIDE
    row_y = np.arange(gh) * STRIDE + 1
    grid = (gh, rig.camera.width // STRIDE)
    return LineTriangulation(rig, row_y, DepthRange()), row_y, grid


def refine(tri, bands, counts, grid, prior_depth, moving=None):
    """One prior depth everywhere, every cell moving unless ``moving`` says: ``(cells
    written, depth grid, predicted error grid)``."""
    prior = np.full(grid, prior_depth, np.float32)
    depth = np.full(grid, np.nan, np.float32)
    std = np.full(grid, np.nan, np.float32)
    moving = np.ones(grid, bool) if moving is None else moving
    n = tri.refine(bands, counts, 1, STRIDE, prior, moving, depth, std)
    return n, depth, std


def cell_x(grid):
    """The camera column of each grid column's cell centre."""
    return np.arange(grid[1]) * STRIDE + 0.5 * (STRIDE - 1)
