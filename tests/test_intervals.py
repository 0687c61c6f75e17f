"""The sparse pattern's line interval predicted from the dense one and the rig."""

from __future__ import annotations

import numpy as np
import pytest

from lightflow.app.core import intervals as intervals_module
from lightflow.app.core.depth_model import DepthRange
from lightflow.app.core.intervals import IntervalModel
from lightflow.app.core.rig import resolve_rig
from lightflow.app.stages import true_flows
from lightflow.drivers.sim.scenes import get_scene
from lightflow.drivers.sim.synthetic import SceneRenderer

STRIDE = 4


def _true_grid(rig, scene, t, exposure=0.005):
    """True intervals (2, h, w) and depth (h, w) at the grid cells, from the renderer."""
    renderer = SceneRenderer(rig, get_scene(scene))
    flows = true_flows(renderer, t, exposure)
    depth = renderer.truth(t + exposure / 2).depth
    ys = np.arange(rig.camera.height // STRIDE) * STRIDE + (STRIDE - 1) // 2
    xs = np.arange(rig.camera.width // STRIDE) * STRIDE + (STRIDE - 1) // 2
    sub = np.ix_(ys, xs)
    return flows.interval[(slice(None), *sub)], depth[sub].astype(np.float64)


@pytest.fixture(scope="module")
def rig():
    # the example rig's patterns: 40 and 18 projector px, the dense one 2x denser or more
    return resolve_rig("two-projector").scaled(0.5)


@pytest.mark.parametrize("scene, t", [("ball", 0.1), ("tilted-board", 0.0)])
def test_prediction_from_true_dense_interval_is_the_true_sparse_one(rig, scene, t, monkeypatch):
    """Given the true dense interval and depth, the predicted sparse interval is the true one.

    Every cell is predicted here, however alike the two intervals (DENSER = 1), and
    however much the depth moves the prediction (DEPTH_TOLERANCE = 0: the geometry
    alone; the depth test is below).  Measured: median 0.1-0.3 %, p90 under 1 % (the
    tables' interpolation and the finite differences of the truth).
    """
    monkeypatch.setattr(intervals_module, "DENSER", 1.0)
    monkeypatch.setattr(intervals_module, "DEPTH_TOLERANCE", 0.0)
    intervals, depth = _true_grid(rig, scene, t)
    model = IntervalModel(rig, STRIDE, DepthRange())
    lg, have = model.disagreement(intervals, depth)
    on = have.sum(axis=0) > 0
    assert on.sum() > 200
    err = np.abs(lg.sum(axis=0)[on])
    assert np.median(err) < 0.005, np.percentile(err, [50, 90])
    assert np.percentile(err, 90) < 0.015, np.percentile(err, [50, 90])


def test_no_correction_on_a_plane_with_noisy_intervals(rig, monkeypatch):
    """A tilted plane does not bend its intervals: 1 % noise on them changes no flow.

    Every cell is predicted (DENSER = 1): the curvature test alone keeps them.
    """
    monkeypatch.setattr(intervals_module, "DENSER", 1.0)
    intervals, depth = _true_grid(rig, "tilted-board", 0.0)
    rng = np.random.default_rng(1)
    noisy = intervals * (1 + 0.01 * rng.standard_normal(intervals.shape))
    model = IntervalModel(rig, STRIDE, DepthRange())
    fix = model.correct(noisy.astype(np.float32), depth)
    on = np.isfinite(noisy).all(axis=0) & np.isfinite(depth)
    assert on.sum() > 1000
    assert np.count_nonzero(fix[:, on]) < 0.01 * on.sum()


def test_a_ball_whose_sparse_interval_is_short_is_corrected(rig, monkeypatch):
    """The sparse interval measured 8 % short on a ball is put back to the tolerance.

    The correction is soft (the disagreement beyond DISAGREE_LOG): what is left is
    the tolerance, 3 %, where the ball bends its intervals.  On this rig a depth 5 %
    off moves nearly every prediction by more than the tolerance, so the depth test
    (below) is off here (DEPTH_TOLERANCE = 0): this tests the correction itself.
    """
    monkeypatch.setattr(intervals_module, "DEPTH_TOLERANCE", 0.0)
    intervals, depth = _true_grid(rig, "ball", 0.1)
    sparse = int(np.nanmedian(intervals[1]) > np.nanmedian(intervals[0]))
    measured = intervals.copy()
    measured[sparse] *= 0.92
    model = IntervalModel(rig, STRIDE, DepthRange())
    fix = model.correct(measured.astype(np.float32), depth)
    on = np.isfinite(measured).all(axis=0) & np.isfinite(depth) & (fix[sparse] != 0)
    assert on.sum() > 100
    after = np.log(measured[sparse][on] / intervals[sparse][on]) - fix[sparse][on]
    tol = intervals_module.DISAGREE_LOG
    assert abs(np.median(after)) < tol + 0.005, np.median(after)


def test_no_prediction_where_the_depth_moves_it_beyond_the_tolerance(rig, monkeypatch):
    """A prediction is made only where a depth off by DEPTH_TOLERANCE either way moves
    it by at most DISAGREE_LOG: the depth comes from flows the measured interval
    biases, and a prediction that follows the depth would hold that bias.

    Checked cell by cell against the predictions at the depth and 5 % either side
    (the test off).  On this rig, with its projectors on either side of the camera,
    nearly every cell of the ball fails it.
    """
    monkeypatch.setattr(intervals_module, "DENSER", 1.0)
    intervals, depth = _true_grid(rig, "ball", 0.1)
    model = IntervalModel(rig, STRIDE, DepthRange())
    tol = intervals_module.DEPTH_TOLERANCE
    assert tol > 0
    gated, have = model.disagreement(intervals, depth)
    monkeypatch.setattr(intervals_module, "DEPTH_TOLERANCE", 0.0)
    lg, base = model.disagreement(intervals, depth)
    lg_near, have_near = model.disagreement(intervals, depth * (1 - tol))
    lg_far, have_far = model.disagreement(intervals, depth * (1 + tol))
    on = (base.sum(axis=0) > 0) & (have_near.sum(axis=0) > 0) & (have_far.sum(axis=0) > 0)
    assert on.sum() > 200
    moved = np.maximum(np.abs(lg_near - lg), np.abs(lg_far - lg)).sum(axis=0)
    kept = have.sum(axis=0) > 0
    margin = 1e-3  # the test interpolates the depth tables at slightly other depths
    steady = moved < intervals_module.DISAGREE_LOG - margin
    shaky = moved > intervals_module.DISAGREE_LOG + margin
    assert (kept[on & steady]).all()
    assert not (kept[on & shaky]).any()
    assert np.allclose(gated[:, kept], lg[:, kept])


@pytest.mark.parametrize("scene, t", [("ball", 0.1), ("tilted-board", 0.0), ("board", 0.0)])
def test_depth_from_the_true_intervals_is_the_true_depth(rig, scene, t):
    """Two intervals, two unknowns (depth, dz/dx): the true intervals give the true depth.

    Measured: a depth on 97-100 % of the cells (not at a ball's very limb), median
    0.01-0.05 %, p90 0.04-0.4 % of the depth (the tables' interpolation, the finite
    differences of the truth at the limb).
    """
    intervals, depth = _true_grid(rig, scene, t)
    model = IntervalModel(rig, STRIDE, DepthRange())
    z, sens = model.depth(intervals)
    on = np.isfinite(intervals).all(axis=0) & np.isfinite(depth)
    assert on.sum() > 200
    rel = np.abs(z[on] / depth[on] - 1.0)
    share = np.isfinite(rel).mean()
    assert share > 0.95
    rel = rel[np.isfinite(rel)]
    print(f"\n{scene}: depth on {100 * share:.1f} %, |z / truth - 1| median "
          f"{100 * np.median(rel):.3f} %, p90 {100 * np.percentile(rel, 90):.3f} %; "
          f"sensitivity {np.nanmedian(sens[on]):.2f}")
    assert np.median(rel) < 0.001
    assert np.percentile(rel, 90) < 0.006
    # an interval ratio off by e moves the log depth by about e / sensitivity
    assert 0.1 < np.nanmedian(sens[on]) < 5.0


def test_no_depth_from_intervals_the_rig_cannot_make(rig):
    """Interval pairs that no depth in the working range explains give no depth."""
    intervals, _ = _true_grid(rig, "board", 0.0)
    model = IntervalModel(rig, STRIDE, DepthRange())
    wrong = intervals.copy()
    wrong[1] *= 3.0  # the second pattern's lines three times as far apart as any depth makes
    z, sens = model.depth(wrong)
    assert np.isnan(z).all() and np.isnan(sens).all()


def test_a_pole_of_the_prediction_is_no_depth():
    """Generated rig 9 of the evaluation's tuning seeds: on its board (0.6 m) the residual of
    the true intervals just touches 0 at the true depth, and sparse intervals measured
    1-2 % short lift it off; the only sign change left is a pole of the predicted interval
    near 0.36 m, where the dense pattern's du/dx passes through 0.  No depth there, or the
    true one: never the pole's (it gave boards 240 mm too near, p90 257 mm)."""
    from lightflow.app.core.rig import rig_from_dict
    from lightflow.app.eval_matrix import cropped, generated_rig

    rig9 = cropped(rig_from_dict(generated_rig(9), "gen9"), (400, 300))
    intervals, depth = _true_grid(rig9, "slow-board", 0.0)
    model = IntervalModel(rig9, STRIDE, DepthRange())
    on = np.isfinite(intervals).all(axis=0) & np.isfinite(depth)
    assert on.sum() > 200
    for short in (1.0, 0.99, 0.98):
        measured = intervals.copy()
        measured[1] *= short
        z, sens = model.depth(measured)
        rel = np.abs(z[on] / depth[on] - 1.0)
        found = np.isfinite(rel)
        print(f"\nsparse x {short}: depth on {100 * found.mean():.0f} %, |z / truth - 1| "
              f"max {np.max(rel[found], initial=0.0):.3f}")
        assert not np.any(rel[found] > 0.1), short
        assert not np.any(sens[on][found] > intervals_module.MAX_SENSITIVITY)
