"""The flow stage on hand-made band maps: gating of static and overlapping bands."""

import cv2
import numpy as np
import pytest

from lightflow.app.core import causes
from lightflow.app.core.flow import FlowModel, FlowParams, _enclosed, _gauss, smooth_log_ratio
from lightflow.app.core.rig import resolve_rig


def _grids(m, B, ramp=1.2, slant=0.0, shape=(4, 5)):
    g = np.empty((2, 4) + shape)
    for p in range(2):
        g[p, 0], g[p, 1], g[p, 2], g[p, 3] = m[p], B[p], ramp, slant
    return g


def test_flows_and_log_ratio_from_long_bands():
    rig = resolve_rig("two-projector")
    model = FlowModel(rig)
    model.blur[:] = (0.3, 0.0)  # a known, small blur: long bands need no correction
    (_, pat1), (_, pat2) = rig.patterns
    # bands three times longer than their line: the width at half height is the sweep
    out = model.combine(_grids((16.0, 20.0), (60.0, 40.0)), FlowParams())
    log_ratio, flows = out.log_ratio, out.flows
    assert np.allclose(flows[0], 16.0 / 60.0 * pat1.pitch_px, rtol=2e-3)
    assert np.allclose(flows[1], 20.0 / 40.0 * pat2.pitch_px, rtol=2e-3)
    assert np.allclose(log_ratio, np.log(16.0 / 60.0) - np.log(20.0 / 40.0), atol=3e-3)


def test_static_and_overlapping_bands_give_no_flow():
    rig = resolve_rig("two-projector")
    model = FlowModel(rig)
    model.blur[:] = (0.3, 0.0)
    # pattern 2: 3 px lines at 18 px pitch seen with B = 36 px are 6 px wide
    static = model.combine(_grids((16.0, 6.3), (60.0, 36.0)), FlowParams())
    assert np.isnan(static.log_ratio).all()
    assert (static.why == causes.STATIC).all()
    overlapping = model.combine(_grids((16.0, 30.0), (60.0, 36.0)), FlowParams())
    assert np.isnan(overlapping.log_ratio).all()
    assert (overlapping.why == causes.OVERLAP).all()
    fine = model.combine(_grids((16.0, 14.0), (60.0, 36.0)), FlowParams())
    assert np.isfinite(fine.log_ratio).all()
    assert (fine.why == causes.DEPTH).all()


def test_bands_longer_than_the_tables_are_measured():
    """Widths beyond the profile tables (48 px) are the sweep itself: no NaN above 48 px."""
    rig = resolve_rig("two-projector")
    model = FlowModel(rig)
    model.blur[:] = (0.5, 0.2)
    (_, pat1), (_, pat2) = rig.patterns
    for m in (47.5, 49.0, 60.0, 90.0):
        out = model.combine(_grids((m, 20.0), (200.0, 40.0)), FlowParams())
        log_ratio, flows = out.log_ratio, out.flows
        assert np.allclose(flows[0], m / 200.0 * pat1.pitch_px, rtol=2e-3)
        assert np.allclose(log_ratio, np.log(m / 200.0) - np.log(20.0 / 40.0), atol=3e-3)


def test_reread_takes_the_corrected_interval_into_the_line_width():
    """Sweeps read again with corrected intervals (the sparse pattern's, predicted).

    A long band's width is its sweep, so only ``L / B`` changes: the flow by
    ``exp(fix)``.  A sweep shorter than the line is read against the line's width,
    which is the interval over the pitch: it changes by more (measured: a factor
    0.955 where ``exp(fix)`` is 0.970).  No correction, no change; a cell the first
    reading left out stays out.
    """
    rig = resolve_rig("two-projector").with_blur([(0.4, 0.0), (0.4, 0.0)])
    model = FlowModel(rig)
    params = FlowParams()
    for m0, ramp, short in ((16.0, 1.2, False), (4.7, 2.0, True)):
        grids = _grids((m0, 14.0), (60.0, 36.0), ramp=ramp)
        first = model.combine(grids, params)
        assert np.isfinite(first.log_ratio).all()
        fix = np.zeros((2,) + grids.shape[2:], np.float32)
        same = model.reread(first, grids, fix, params)
        assert np.array_equal(same.log_ratio, first.log_ratio)
        fix[0] = -0.03  # the predicted interval 3 % longer than the measured one
        again = model.reread(first, grids, fix, params)
        ratio = again.flows[0] / first.flows[0]
        if short:
            assert (np.abs(ratio - np.exp(-0.03)) > 0.01).all(), ratio
        else:
            assert np.allclose(ratio, np.exp(-0.03), rtol=2e-3), ratio
        assert np.allclose(again.flows[1], first.flows[1], rtol=1e-3)
    overlapping = _grids((16.0, 30.0), (60.0, 36.0))
    first = model.combine(overlapping, params)
    again = model.reread(first, overlapping, fix, params)
    assert np.isnan(again.log_ratio).all()
    assert (again.why == causes.OVERLAP).all()


def _smooth_reference(log_ratio, sigma, outlier_sigmas, fill_fraction, variance=None):
    """smooth_log_ratio as numpy passes (before its passes were fused into kernels)."""
    zero = np.float32(0.0)
    planes = [log_ratio.astype(np.float32)]
    if variance is not None:
        planes.append(variance.astype(np.float32))
    mask = np.isfinite(planes[0])
    for extra in planes[1:]:
        mask &= np.isfinite(extra)
    if sigma <= 0:
        return [np.where(mask, v, np.float32(np.nan)) for v in planes]
    lr, keep = planes[0], mask
    if outlier_sigmas > 0:
        k = 2 * int(round(sigma)) + 1
        with np.errstate(invalid="ignore", divide="ignore"):
            first = cv2.blur(np.where(mask, lr, zero), (k, k)) / cv2.blur(
                mask.astype(np.float32), (k, k)
            )
        resid = np.abs(lr - first)
        resid[~mask] = np.nan
        sample = resid[::2, ::2]
        finite = sample[np.isfinite(sample)]
        if finite.size >= 16:
            keep = resid <= outlier_sigmas * (float(np.median(finite)) * 1.4826 + 1e-6)
    inputs = [keep.astype(np.float32)]
    if variance is not None:
        wt = np.where(keep, 1.0 / np.maximum(planes[1], np.float32(1e-12)), zero)
        inputs += [wt, np.where(keep, lr * wt, zero), np.where(keep, planes[1], zero)]
    else:
        inputs.append(np.where(keep, lr, zero))
    den, *blurred = (_gauss(x, sigma) for x in inputs)
    fill = den >= fill_fraction
    if fill_fraction < 1.0:
        fill &= _enclosed(keep, int(2.0 * sigma) + 1) | (den > 0.5)
    fill |= keep
    den[~fill] = np.nan
    if variance is None:
        return [blurred[0] / den]
    blurred[0][~fill] = np.nan
    return [blurred[1] / blurred[0], blurred[2] / den]


@pytest.mark.parametrize("sigma", [0.0, 2.0, 6.0])
@pytest.mark.parametrize("with_variance", [False, True])
@pytest.mark.parametrize("fill_fraction", [0.3, 1.0])
def test_smoothing_gives_the_values_of_its_numpy_passes(sigma, with_variance, fill_fraction):
    rng = np.random.default_rng(3)
    lr = rng.normal(0.1, 0.02, (60, 80)).astype(np.float32)
    lr[rng.random(lr.shape) < 0.3] = np.nan
    lr[rng.random(lr.shape) < 0.02] += 1.0  # outliers
    lr[20:30, 30:50] = np.nan  # a hole
    var = rng.uniform(1e-5, 1e-3, lr.shape) if with_variance else None
    got = smooth_log_ratio(lr, sigma, 3.0, fill_fraction, var)
    got = list(got) if with_variance else [got]
    want = _smooth_reference(lr, sigma, 3.0, fill_fraction, var)
    assert len(got) == len(want)
    for g, w in zip(got, want, strict=True):
        assert g.dtype == np.float32 and np.array_equal(g, w, equal_nan=True)


def test_reading_a_few_cells_again_gives_the_flows_of_reading_them_all():
    """The second reading redoes the blur and decision only near the corrected cells."""
    rig = resolve_rig("two-projector")
    model = FlowModel(rig)
    model.blur[:] = (0.5, 0.2)
    model.stride = 4  # the pipeline's: the sweeps are averaged over sigma = 2 cells
    rng = np.random.default_rng(7)
    shape = (120, 90)
    g = _grids((16.0, 14.0), (60.0, 36.0), shape=shape)
    g[:, 0] *= rng.uniform(0.8, 1.2, (2, *shape))
    g[:, 1] *= rng.uniform(0.97, 1.03, (2, *shape))
    g[:, 0, :, :10] = np.nan  # no bands on one side
    params = FlowParams()
    first = model.combine(g, params)
    fix = np.zeros((2, *shape), np.float32)
    fix[:, [20, 21, 70], [5, 40, 88]] = rng.uniform(-0.05, 0.05, (2, 3))  # a few rows apart
    fixed = g.copy()
    fixed[:, 1] *= np.exp(-fix)
    todo = (fix != 0).any(axis=0)
    again = model.recombine(fixed, params, first=first, todo=todo)
    every = model.recombine(fixed, params)
    assert not np.array_equal(again.log_ratio, first.log_ratio, equal_nan=True)
    for a, b in zip(
        (again.log_ratio, *again.flows, again.lr_var, again.lr_sys, again.why),
        (every.log_ratio, *every.flows, every.lr_var, every.lr_sys, every.why),
        strict=True,
    ):
        assert np.array_equal(a, b, equal_nan=True)


def test_reread_keeps_the_choice_of_its_numpy_passes():
    """reread against the whole second reading and the numpy passes it replaced, with
    added cells and a fallback shift, cells read again in a few places."""
    rig = resolve_rig("two-projector")
    model = FlowModel(rig)
    model.blur[:] = (0.5, 0.2)
    model.stride = 4
    rng = np.random.default_rng(11)
    shape = (150, 140)
    g = _grids((16.0, 14.0), (60.0, 36.0), shape=shape)
    g[:, 0] *= rng.uniform(0.9, 1.1, (2, *shape))
    g[:, 1] *= rng.uniform(0.97, 1.03, (2, *shape))
    g[:, 0, :, :10] = np.nan
    g[:, 0, 100:] *= 0.5  # short sweeps
    params = FlowParams()
    first = model.combine(g, params)
    fix = np.zeros((2, *shape), np.float32)
    fix[:, 20:22, 30:70] = rng.uniform(-0.08, 0.08, (2, 2, 40))
    fix[:, 120, 130:] = -0.05
    fix[1, 102:104, 20:120] = -0.6  # read again, these sweeps fail: the first stands
    added = np.zeros(shape, bool)
    added[60:63, 5:25] = True  # on the edge of the bands, and beyond
    added[110, 50:90] = True
    regrid = g.copy()
    regrid[:, 0, 60:63, 5:25] = 15.0  # bands the first reading did not have
    fallback = np.zeros((2, *shape), np.float32)
    fallback[:, 110, 50:90] = 0.03
    again = model.reread(first, regrid, fix, params, None, added, fallback + fix)
    fixed = regrid.copy()
    fixed[:, 1] *= np.exp(-fix)
    second = model.recombine(fixed, params)
    shift = fallback + fix
    ok = np.isfinite(first.log_ratio) & np.isfinite(second.log_ratio)
    new = added & ~np.isfinite(first.log_ratio) & np.isfinite(second.log_ratio)
    assert ok.any() and new.any() and (~ok & np.isfinite(first.log_ratio)).any()
    want = [np.where(ok, second.log_ratio, first.log_ratio + shift[0] - shift[1])]
    want += [np.where(ok, second.flows[p], first.flows[p] * np.exp(shift[p])) for p in range(2)]
    seconds = (second.log_ratio, *second.flows, second.lr_var, second.lr_sys, second.why)
    firsts = (*want, first.lr_var, first.lr_sys, first.why)
    want = [np.where(new, s, f) for s, f in zip(seconds, firsts, strict=True)]
    want.append(first.swept | (added & second.swept))
    got = (again.log_ratio, *again.flows, again.lr_var, again.lr_sys, again.why, again.swept)
    for a, b in zip(got, want, strict=True):
        assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True)


def test_lines_moved_between_frames_are_told_from_noise_and_from_gaps():
    """A cell moved where either pattern's band width or interval changed by more than
    MOVED_TOLERANCE_PX between two frames that both measured it; noise below it, and a
    cell measured in one frame only, are not a move."""
    from lightflow.app.core.flow import MOVED_TOLERANCE_PX, moved_lines

    rng = np.random.default_rng(3)
    previous = np.full((2, 2, 3, 4), 10.0)
    grids = previous + rng.uniform(-0.8, 0.8, previous.shape) * MOVED_TOLERANCE_PX
    grids[0, 0, 0, 0] += 2.0  # pattern 0's band wider: moved
    grids[1, 1, 1, 1] -= 2.0  # pattern 1's interval shorter: moved
    previous[0, 0, 2, 2] = np.nan  # a band width measured in this frame only: no move
    grids[0, 0, 2, 2] = 30.0
    previous[1, 0, 2, 3] = np.nan  # measured in the previous frame only
    grids[1, 0, 2, 3] = 30.0
    moved = moved_lines(grids, previous)
    assert moved.shape == (3, 4)
    expected = np.zeros((3, 4), bool)
    expected[0, 0] = expected[1, 1] = True
    assert np.array_equal(moved, expected)
