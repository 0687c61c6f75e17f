"""Two rules of the line decision in app/core/triangulation.py, each on a case it alone decides.

Tested through :meth:`LineTriangulation.refine`, with bands placed exactly where a rig's
lines light a known surface (``lit_surface.py``, as in ``test_triangulation.py``):

- the BOTH rule of ``_decide_rows`` (``BOTH_AGREE``, ``BOTH_MARGIN``, ``BOTH_GAP``):
  where two pairs of line offsets agree and neither the margin rule nor the prior rule
  (``PRIOR_REACH``, ``PRIOR_GAP``) decides, the pair that agrees best is taken if it is
  also clearly the nearer to the priors; and not taken when another pair lies nearer
  the priors, nor when the best pair agrees only loosely (a wrong pair, here);
- the lone band of ``_extend_rows``: a decided band whose neighbours are undecided
  passes its next line on to a neighbour when the other pattern's decided depth around
  agrees (``EXTEND_AGREE``), and not when it disagrees, nor onto a wall beyond.

Each test fails on a copy of the module with its rule, or the condition it guards,
taken out (checked when the tests were written; the values measured with and without
are in the tests' docstrings).
"""

import json
from pathlib import Path

import numpy as np
import pytest
from lit_surface import cell_x, refine, surface_bands, triangulation

from lightflow.app.core.bands import F_CENTRE
from lightflow.app.core.rig import load_rig, rig_from_dict

RIGS = Path(__file__).resolve().parents[1] / "app" / "rigs"
Z = 0.75


# ---------------------------------------------------------------- the BOTH rule


def one_projector_rig(scale, pitch_1):
    """The single-projector rig with two uniform patterns, pitch ``40 * scale`` and
    ``pitch_1`` (projector px), its projector ``scale`` times as wide and as long in
    focus (the same field and per-line depths, finer columns).

    With ``pitch_1`` near half the first pitch, two lines of the second pattern are
    one of the first, to ``2 * pitch_1 - 40 * scale`` projector px: the pairs of offsets
    (0, 0) and (+-1, +-2) all agree, the wrong ones to that many px of depth (a line
    is about 5 % of the depth at 0.75 m; one projector px 0.16 % / ``scale``).  Half-
    integer pitches keep every line centred exactly (a 3 px line lights whole columns).
    """
    data = json.loads((RIGS / "single-projector.json").read_text())
    proj = data["projectors"][0]
    proj["width"] = int(1280 * scale)
    proj["K"][0][0] = 1500.0 * scale
    proj["K"][0][2] = (proj["width"] - 1) / 2
    proj["patterns"] = [
        {"channel": "red", "kind": "uniform", "pitch_px": 40.0 * scale, "width_px": 3.0,
         "offset_px": 0.0},
        {"channel": "blue", "kind": "uniform", "pitch_px": pitch_1, "width_px": 3.0,
         "offset_px": 7.0},
    ]  # fmt: skip
    return rig_from_dict(data)


def patch(x):
    """A board at 0.75 m seen over x 500-1100 only (a dark background around it: the
    runs are short, so every candidate line of every band lies inside the pattern)."""
    return np.where(np.abs(x - 800.0) < 300.0, Z, np.nan)


@pytest.fixture(scope="module")
def near_half_pitch():
    """Pitches 120 and 60.5 at scale 3: the wrong pairs agree to 0.06 % (right: 0.00 %),
    below the margin rule's reach (the runner-up must disagree by more than 0.1 %)."""
    rig = one_projector_rig(3, 60.5)
    tri, row_y, grid = triangulation(rig)
    bands, counts = surface_bands(rig, tri, row_y, patch)
    return tri, bands, counts, grid


def test_both_rule_takes_the_pair_that_agrees_best_and_is_nearest_the_prior(near_half_pitch):
    """The prior 2.5 % long: the right pair lies 2.4 % from it, the nearer wrong one
    (+7 %) 4.8 %, not the prior rule's 4 % farther but more than BOTH_GAP's 1 %.  The
    right pair agrees best (runner-up 0.06 %, BOTH_MARGIN times worse and more): every
    cell of the board gets its exact depth.  (Measured: 43800 cells, 0.0001 mm off at
    most; without the BOTH rule, 0 cells.)"""
    tri, bands, counts, grid = near_half_pitch
    n, depth, _ = refine(tri, bands, counts, grid, Z * 1.025)
    have = np.isfinite(depth)
    on_board = np.abs(cell_x(grid) - 800.0) < 280.0
    err = np.abs(depth[have] - Z)
    print(f"\n{n} cells; max error {err.max(initial=0.0) * 1e3:.4f} mm")
    assert have[:, on_board].all()
    assert n > 40000
    assert err.max() < 1e-5


def test_both_rule_takes_no_pair_nearer_the_prior_that_agrees_worse(near_half_pitch):
    """The prior 5 % long: now a wrong pair (+7 %) is the nearer to it, 2.3 % against the
    right pair's 4.7 %, but the right pair still agrees best: nothing is written, where
    taking the nearer pair would put the board 55 mm too far.  (Measured: 0 cells;
    without the 'agrees best' condition, 43800 cells 55-64 mm off.)"""
    tri, bands, counts, grid = near_half_pitch
    n, depth, _ = refine(tri, bands, counts, grid, Z * 1.05)
    assert n == 0 and not np.isfinite(depth).any()


def test_both_rule_takes_no_pair_that_agrees_only_loosely():
    """Pitches 40 and 21: the wrong pairs agree to 0.3 % (the runner-up's margin rule
    decides exact bands).  The second pattern's centres biased 4.6 px to the right make
    a wrong pair (7 % of the depth off) agree best, at 0.22 % (over BOTH_AGREE's 0.15 %),
    the right one at 0.55 % (BOTH_MARGIN times worse and more, too little for the margin
    rule), the prior at the board (the wrong pair the only one within AGREE, out of the
    prior rule's 4 % reach): nothing is written.  (Measured: 0 cells; without the
    BOTH_AGREE condition, 46200 cells 54-62 mm off.)"""
    rig = one_projector_rig(1, 21.0)
    tri, row_y, grid = triangulation(rig)
    bands, counts = surface_bands(rig, tri, row_y, patch)
    bands[1, :, :, F_CENTRE] += 4.6
    n, depth, _ = refine(tri, bands, counts, grid, Z)
    assert n == 0 and not np.isfinite(depth).any()


# ---------------------------------------------------------------- a lone band carried on


def lone_band_case(depth_of_x):
    """The two-projector rig, the surface ``depth_of_x``; in every row, the second
    pattern's bands kept only between the first pattern's band A at x 1216 and its next
    band B at x 1317 (four bands, the last 2/3 of its spacing before B), the others
    taken out (NaN).

    So the flows' depth decides A (the first pattern's one band among the second's)
    and the second pattern's four bands; A's neighbours stay undecided, so A stands
    alone, and B lies within one of the second pattern's spacings of its last band
    (where :func:`_other_depth` still gives a depth)."""
    rig = load_rig(RIGS / "two-projector.json")
    tri, row_y, grid = triangulation(rig)
    bands, counts = surface_bands(rig, tri, row_y, depth_of_x)
    x0 = bands[0, :, :, F_CENTRE]
    x1 = bands[1, :, :, F_CENTRE]
    a = np.nanargmin(np.abs(x0 - 1216.0), axis=1)
    rows = np.arange(len(row_y))
    xa, xb = x0[rows, a], x0[rows, a + 1]
    keep = (x1 > xa[:, None] - 25.0) & (x1 < xb[:, None])
    x1[~keep] = np.nan
    assert np.all(np.abs(xa - 1216.5) < 0.5) and np.all(keep.sum(axis=1) == 4)
    return tri, bands, counts, grid, xb


def board(x):
    return np.full(x.shape, Z)


def test_a_lone_decided_band_passes_its_next_line_on():
    """B gets A's next line where the second pattern's depth, carried on from its four
    bands, agrees: the cells from the second pattern's last band to B (x 1298-1317)
    and half a spacing beyond get the board's depth.  (Measured: 12900 cells written,
    0.0001 mm off, to x 1366 in every row; without the lone band's carry, 8700, to x
    1310.)"""
    tri, bands, counts, grid, xb = lone_band_case(board)
    n, depth, _ = refine(tri, bands, counts, grid, Z)
    have = np.isfinite(depth)
    x = cell_x(grid)
    print(f"\n{n} cells, x {x[have.any(axis=0)].min():.0f}-{x[have.any(axis=0)].max():.0f}")
    assert np.max(np.abs(depth[have] - Z)) < 1e-5
    # between the second pattern's last band (x 1297.6) and B, and past B
    assert have[:, (x > 1305.0) & (x < 1360.0)].all()
    assert n > 12000


def test_a_lone_band_is_carried_no_further_onto_a_wall():
    """The same board, a wall at 0.9 m from x 1380 (beyond B's reach of half a
    spacing): B is carried on as before, the wall's bands past it get nothing (the
    second pattern has no depth there).  (Measured: 13800 cells, to x 1378: B's spacing
    to the wall's first band is wider, and so is its reach; none on the wall.)"""

    def board_and_wall(x):
        return np.where(x < 1380.0, Z, 0.9)

    tri, bands, counts, grid, xb = lone_band_case(board_and_wall)
    n, depth, _ = refine(tri, bands, counts, grid, Z)
    have = np.isfinite(depth)
    x = cell_x(grid)
    print(f"\n{n} cells, to x {x[have.any(axis=0)].max():.0f}")
    assert have[:, (x > 1305.0) & (x < 1360.0)].all()
    assert not have[:, x > 1380.0].any()
    assert np.max(np.abs(depth[have] - Z)) < 1e-5


def test_a_lone_band_is_not_carried_where_the_other_pattern_disagrees():
    """B moved 6 px to the right (a band not quite where the board puts A's next
    line): the depth on that line there is 0.4 % short of the second pattern's, beyond
    EXTEND_AGREE's 0.3 %: B gets no line, and no cell beyond the second pattern's bands
    a depth.  (Measured: 8700 cells, to x 1310, as without the carry; with the carry
    taking B regardless of the other pattern, 13500 cells, to x 1374, up to 5.8 mm
    off.)"""
    tri, bands, counts, grid, xb = lone_band_case(board)
    rows = np.arange(grid[0])
    b = np.nanargmin(np.abs(bands[0, :, :, F_CENTRE] - xb[:, None]), axis=1)
    bands[0, rows, b, F_CENTRE] += 6.0
    n, depth, _ = refine(tri, bands, counts, grid, Z)
    have = np.isfinite(depth)
    x = cell_x(grid)
    print(f"\n{n} cells, to x {x[have.any(axis=0)].max():.0f}")
    assert np.max(np.abs(depth[have] - Z)) < 1e-5
    assert not have[:, x > 1320.0].any()
