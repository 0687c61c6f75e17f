"""Band centres exactly where a rig's lines light a known surface: the triangulation
tests' input (no detector, no image)."""

import numpy as np

from lightflow.app.core.bands import F_CENTRE, N_FIELDS
from lightflow.app.core.geometry import project_to_projector


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
