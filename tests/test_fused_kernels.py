"""Kernels that replaced numpy passes give the values of those passes, bit for bit.

Each test keeps the numpy code a kernel replaced (or the whole-map call a partial one
stands for) as the reference, on maps with NaN, infinities and zeros.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from lightflow.app.core import causes as cz
from lightflow.app.core import intervals as iv
from lightflow.app.core.depth_model import (
    DepthLUT,
    DepthRange,
    depth_and_slope,
    lookup_depth,
    update_depth_and_slope,
)
from lightflow.app.core.flow import FlowMaps, _blur_busy, _gauss, _gauss_window
from lightflow.app.core.intervals import IntervalModel
from lightflow.app.core.pipeline import (
    INTERVAL_FLOOR,
    INTERVAL_NOISE,
    _interval_variance,
    _join_interval_depth,
)
from lightflow.app.core.rig import resolve_rig


def _spiked(rng, shape, share=0.05, lo=0.0, hi=1.0):
    """Uniform values with a ``share`` of NaN, +-inf and 0."""
    x = rng.uniform(lo, hi, shape)
    spikes = rng.random(shape) < share
    x[spikes] = rng.choice([np.nan, np.inf, -np.inf, 0.0], np.count_nonzero(spikes))
    return x


def test_lut_planes_hold_the_table():
    rng = np.random.default_rng(0)
    table = rng.random((5, 7, 22)).astype(np.float32)
    lut = DepthLUT(4, np.zeros((5, 7), np.float32), np.ones((5, 7), np.float32), table)
    assert np.array_equal(lut.table, table)
    assert lut.planes.shape == (22, 5, 7) and lut.planes.flags.c_contiguous
    assert np.array_equal(lut.planes, np.moveaxis(table, 2, 0))
    assert lut.nbytes == 2 * 5 * 7 * 4 + table.nbytes


def _random_lut(rng, h, w, m, unusable=0):
    """A depth table of random samples: ``(lut, table, h0, inv_dh)``; the first
    ``unusable`` pixels of row 0 have no usable samples."""
    table = rng.uniform(0.4, 3.0, (h, w, m)).astype(np.float32)
    h0 = rng.uniform(-0.5, 0.0, (h, w)).astype(np.float32)
    inv_dh = rng.uniform(5.0, 30.0, (h, w)).astype(np.float32)
    inv_dh[0, :unusable] = 0.0
    return DepthLUT(4, h0, inv_dh, table), table, h0, inv_dh


def test_lookup_reads_the_catmull_rom_of_each_pixel():
    """The sample-major lookup against the spline written out per pixel."""
    rng = np.random.default_rng(1)
    h, w, m = 6, 9, 22
    lut, table, h0, inv_dh = _random_lut(rng, h, w, m, unusable=3)
    logr = _spiked(rng, (h, w), lo=-0.6, hi=1.5).astype(np.float32)
    z = lookup_depth(lut, logr)
    for i in range(h):
        for j in range(w):
            t = (logr[i, j] - h0[i, j]) * inv_dh[i, j]
            if not (inv_dh[i, j] > 0 and np.isfinite(logr[i, j]) and 0 <= t <= m - 1):
                assert np.isnan(z[i, j])
                continue
            row = table[i, j]
            j1 = min(int(t), m - 2)
            f = t - j1
            p1, p2 = row[j1], row[j1 + 1]
            p0 = row[j1 - 1] if j1 > 0 else 2 * p1 - p2
            p3 = row[j1 + 2] if j1 + 2 < m else 2 * p2 - p1
            a, b, c = p2 - p0, 2 * p0 - 5 * p1 + 4 * p2 - p3, 3 * (p1 - p2) + p3 - p0
            expected = np.float32(1.0 / (p1 + 0.5 * f * (a + f * (b + f * c))))
            assert z[i, j] == pytest.approx(expected, rel=1e-6)


def test_depth_looked_up_again_where_the_log_ratio_changed_is_the_whole_lookup():
    rng = np.random.default_rng(4)
    h, w, m = 30, 40, 22
    lut = _random_lut(rng, h, w, m)[0]
    before = _spiked(rng, (h, w), lo=-0.6, hi=1.5).astype(np.float32)
    now = before.copy()
    changed = rng.random((h, w)) < 0.2
    now[changed] = _spiked(rng, (h, w), lo=-0.6, hi=1.5).astype(np.float32)[changed]
    z, slope = depth_and_slope(lut, before)
    update_depth_and_slope(lut, now, before, z, slope)
    want = depth_and_slope(lut, now)
    assert np.array_equal(z, want[0], equal_nan=True)
    assert np.array_equal(slope, want[1], equal_nan=True)


@pytest.mark.parametrize("rows", [[], [3], [40, 41, 42, 90], list(range(10, 60))])
def test_blur_of_the_busy_rows_is_the_whole_blur(rows):
    rng = np.random.default_rng(len(rows))
    stack = np.zeros((120, 50, 6), np.float32)
    stack[rows] = rng.random((len(rows), 50, 6)).astype(np.float32)
    busy = np.zeros(120, bool)
    busy[rows] = True
    assert np.array_equal(_blur_busy(stack, 2.0, busy), _gauss(stack, 2.0))


@pytest.mark.parametrize("channels", [6, 7])
@pytest.mark.parametrize("width", [400, 403, 57])
def test_blur_of_a_window_is_the_whole_blur(channels, width):
    """Windows of any size and place, up to the map's edges (where OpenCV's last few
    values of a row are its own)."""
    rng = np.random.default_rng(width + channels)
    stack = rng.random((90, width, channels)).astype(np.float32)
    stack[rng.random((90, width)) < 0.5] = 0.0
    whole = _gauss(stack, 2.0)
    for _ in range(60):
        r0, c0 = rng.integers(0, 89), rng.integers(0, width - 1)
        r1, c1 = rng.integers(r0 + 1, 91), rng.integers(c0 + 1, width + 1)
        out = np.full_like(stack, np.nan)
        _gauss_window(stack, 2.0, out, r0, r1, c0, c1)
        # bit for bit on this machine's OpenCV (windows start on 16 columns); another build
        # may round a window's first or last vector differently: float rounding only
        np.testing.assert_allclose(out[r0:r1, c0:c1], whole[r0:r1, c0:c1], rtol=1e-6,
                                   atol=1e-7, err_msg=str((r0, r1, c0, c1)))  # fmt: skip


def test_screen_is_the_numpy_screen():
    rng = np.random.default_rng(2)
    shape = (40, 60)
    raw = _spiked(rng, shape, lo=-1.0, hi=1.0).astype(np.float32)
    depth = _spiked(rng, shape, lo=0.3, hi=3.0).astype(np.float32)
    slope = _spiked(rng, shape, lo=0.0, hi=2.0).astype(np.float32)
    lr_var = _spiked(rng, shape, lo=-1e-4, hi=1e-3).astype(np.float32)
    lr_sys = _spiked(rng, shape, lo=-0.02, hi=0.02).astype(np.float32)
    why = rng.integers(0, 5, shape).astype(np.uint8)
    gain, floor, max_rel = 4.0 * 0.11, 0.01**2, 0.05
    maps = FlowMaps(raw, [raw, raw], [1.0, 1.0], lr_var, lr_sys, why.copy(), raw > 0)
    kept, var = maps.screen(depth, slope, gain, floor, max_rel)
    # the numpy passes it replaced (DepthPipeline.process)
    expected_why = why.copy()
    expected_why[np.isfinite(raw) & ~np.isfinite(depth)] = cz.DEPTH_RANGE
    with np.errstate(invalid="ignore", over="ignore"):
        std = np.sqrt(lr_var * gain + lr_sys**2 + floor) * slope
        uncertain = std > max_rel * depth
    expected_why[uncertain] = cz.UNCERTAIN
    assert np.array_equal(maps.why, expected_why)
    assert kept.dtype == var.dtype == np.float32
    assert np.array_equal(kept, np.where(np.isfinite(depth) & ~uncertain, raw, np.nan),
                          equal_nan=True)  # fmt: skip
    with np.errstate(over="ignore"):
        assert np.array_equal(var, std * std, equal_nan=True)


def _numpy_curved(model, intervals, sparse, sparse_interval):
    """:meth:`IntervalModel._curved` as numpy passes (before its kernels)."""
    dense = np.where(np.isfinite(intervals[1 - sparse]), intervals[1 - sparse], 0.0)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        b = (cv2.GaussianBlur(dense.astype(np.float32), (0, 0), iv.SMOOTH_CELLS)
             / cv2.GaussianBlur((dense > 0).astype(np.float32), (0, 0), iv.SMOOTH_CELLS))
        h = int(round(sparse_interval / (2 * model.stride)))
        if h < 1 or 2 * h >= b.shape[1]:
            return np.zeros(b.shape, bool)
        side = np.full(b.shape, np.nan, np.float32)
        side[:, h:-h] = 0.5 * (b[:, : -2 * h] + b[:, 2 * h :])
        valid = dense > 0
        side[:, h:-h][~(valid[:, : -2 * h] & valid[:, 2 * h :])] = np.nan
        return np.abs(side / b - 1.0) > iv.CURVED


@pytest.mark.parametrize("share", [0.0, 0.05, 0.3])
def test_curved_is_the_numpy_test(share):
    rig = resolve_rig("two-projector").scaled(0.25)
    model = IntervalModel(rig, 4, DepthRange())
    rng = np.random.default_rng(int(share * 100))
    shape = (2, rig.camera.height // 4, rig.camera.width // 4)
    # smooth intervals with a bend, then spikes
    x = np.linspace(0.0, 1.0, shape[2])
    intervals = np.empty(shape)
    intervals[0] = 20.0 + 3.0 * np.sin(6.0 * x) + rng.normal(0, 0.05, shape[1:])
    intervals[1] = 45.0 + 8.0 * x * x + rng.normal(0, 0.05, shape[1:])
    spikes = rng.random(shape) < share
    intervals[spikes] = rng.choice([np.nan, np.inf, -np.inf, 0.0, -3.0], np.count_nonzero(spikes))
    for sparse in (0, 1):
        for reach in (8.0, 45.0, 2.0, 1e4):
            expected = _numpy_curved(model, intervals, sparse, reach)
            assert np.array_equal(model._curved(intervals, sparse, reach), expected)


def test_interval_depth_kernels_are_their_numpy_passes():
    """DepthPipeline._depth_from_intervals' variance and last step against the numpy
    passes they replaced."""
    rng = np.random.default_rng(5)
    shape = (50, 70)
    intervals = _spiked(rng, (2, *shape), lo=5.0, hi=80.0)
    sens = _spiked(rng, shape, lo=-2.0, hi=2.0).astype(np.float32)
    cells = 4.0 * np.pi * 6.0 * 6.0 * 4
    var = np.empty(shape, np.float32)
    _interval_variance(intervals, sens, cells, INTERVAL_NOISE**2, INTERVAL_FLOOR**2, var, 0, 50)
    with np.errstate(invalid="ignore", divide="ignore"):
        bands = np.maximum(1.0, cells / intervals.mean(axis=0))
        want = (INTERVAL_NOISE**2 / bands + INTERVAL_FLOOR**2) / (sens * sens)
    assert np.array_equal(var, want.astype(np.float32), equal_nan=True)

    z = _spiked(rng, shape, lo=0.2, hi=3.0).astype(np.float32)
    var = _spiked(rng, shape, lo=0.0, hi=0.01).astype(np.float32)
    depth = _spiked(rng, shape, share=0.4, lo=0.2, hi=3.0).astype(np.float32)
    std = _spiked(rng, shape, lo=0.001, hi=0.2).astype(np.float32)
    swept, curved = rng.random(shape) < 0.8, rng.random(shape) < 0.3
    max_std, near, far = 0.05, 0.3, 2.7
    got_depth, got_std = depth.copy(), std.copy()
    _join_interval_depth(z, var, swept, curved, np.float32(max_std), np.float32(near),
                         np.float32(far), got_depth, got_std, 0, 50)  # fmt: skip
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        s = z * np.sqrt(var)
        ok = (s <= max_std * z) & (z >= near) & (z <= far)
        fill = ~np.isfinite(depth) & ok
        both = np.isfinite(depth) & ok & swept & ~curved
        w_flow = 1.0 / np.square(std[both])
        w_int = 1.0 / np.square(s[both])
        depth[both] = (depth[both] * w_flow + z[both] * w_int) / (w_flow + w_int)
        std[both] = 1.0 / np.sqrt(w_flow + w_int)
    depth[fill] = z[fill]
    std[fill] = s[fill]
    assert fill.any() and both.any()
    assert np.array_equal(got_depth, depth, equal_nan=True)
    assert np.array_equal(got_std, std, equal_nan=True)
