"""Depth model: h_p(z), its LUT inverse, the LUT size and cache, degenerate rigs."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest

from lightflow.app.core import depth_model
from lightflow.app.core.depth_model import (
    LUT_SAMPLES,
    DepthRange,
    build_lut,
    depth_and_slope,
    h_function,
    load_or_build_lut,
    lookup_depth,
)
from lightflow.app.core.errors import ConfigError
from lightflow.app.core.geometry import camera_rays, project_to_projector
from lightflow.app.core.patterns import line_centres
from lightflow.app.core.pipeline import DepthPipeline, PipelineConfig
from lightflow.app.core.rig import rig_from_dict

RIGS = Path(__file__).resolve().parents[1] / "app" / "rigs"
STRIDE = 8
RANGE = DepthRange(0.3, 3.0)
CAM_DIST = [-0.12, 0.05, 0.001, -0.0008, 0.0]
PROJ_DIST = [0.05, -0.02, 0.0, 0.0, 0.0]


def rig_dict(name: str) -> dict:
    return json.loads((RIGS / f"{name}.json").read_text())


def distorted_dict() -> dict:
    d = rig_dict("two-projector")
    d["camera"]["dist"] = list(CAM_DIST)
    for p in d["projectors"]:
        p["dist"] = list(PROJ_DIST)
    return d


RIG_DICTS = {
    "two-projector": lambda: rig_dict("two-projector"),
    "single-projector": lambda: rig_dict("single-projector"),
    "two-projector-distorted": distorted_dict,
}


@pytest.fixture(scope="module")
def rigs():
    return {name: rig_from_dict(make(), name) for name, make in RIG_DICTS.items()}


@pytest.fixture(scope="module")
def luts(rigs):
    return {name: build_lut(rig, STRIDE, RANGE) for name, rig in rigs.items()}


# ------------------------------------------------------------------ round trip


@pytest.mark.parametrize("name", list(RIG_DICTS))
def test_true_flow_ratio_round_trips_to_depth(name, rigs, luts):
    rig, lut = rigs[name], luts[name]
    rays = camera_rays(rig.camera, STRIDE)
    gh, gw = rays.shape[:2]
    assert lut.h0.shape == (rig.camera.height // STRIDE, rig.camera.width // STRIDE) == (gh, gw)
    assert lut.table.shape == (gh, gw, LUT_SAMPLES)
    assert lut.usable.mean() > 0.99

    rng = np.random.default_rng(11)
    n = 3000
    flat_idx = rng.choice(gh * gw, size=n, replace=False)
    ii, jj = np.unravel_index(flat_idx, (gh, gw))
    z = rng.uniform(0.5, 1.0, n)
    h = h_function(rig, np.ascontiguousarray(rays[ii, jj, :2]), z)
    assert np.all(np.isfinite(h))

    grid = np.full((gh, gw), np.nan, np.float32)
    grid[ii, jj] = h
    depth = lookup_depth(lut, grid)
    assert depth.shape == (gh, gw) and depth.dtype == np.float32
    err = np.abs(depth[ii, jj].astype(np.float64) - z)
    print(f"\n{name}: round trip |z - lookup(h(z))| max {err.max() * 1e3:.4f} mm, "
          f"p99 {np.percentile(err, 99) * 1e3:.4f} mm over {n} grid pixels")  # fmt: skip
    assert np.all(np.isfinite(err))
    assert err.max() < 1e-4  # 0.1 mm
    # pixels without a measurement stay without depth
    others = np.ones((gh, gw), bool)
    others[ii, jj] = False
    assert np.all(np.isnan(depth[others]))


@pytest.mark.parametrize("name", list(RIG_DICTS))
def test_flow_ratio_outside_the_table_has_no_depth(name, luts):
    lut = luts[name]
    ok = lut.usable
    lo = lut.h0.astype(np.float64)
    span = np.zeros_like(lo)
    span[ok] = (LUT_SAMPLES - 1) / lut.inv_dh[ok].astype(np.float64)
    below = np.where(ok, lo - 0.05 * span, 0.0).astype(np.float32)
    above = np.where(ok, lo + 1.05 * span, 0.0).astype(np.float32)
    assert np.all(np.isnan(lookup_depth(lut, below)))
    assert np.all(np.isnan(lookup_depth(lut, above)))
    # inside the table, every usable pixel has a depth in the working range
    inside = lookup_depth(lut, np.where(ok, lo + 0.5 * span, np.nan).astype(np.float32))
    assert np.all(np.isfinite(inside[ok]))
    assert np.all((inside[ok] >= RANGE.near * 0.999) & (inside[ok] <= RANGE.far * 1.001))


def test_depth_and_slope_is_the_lookup_and_its_derivative(luts):
    """The slope is the lookup's own derivative: central differences agree within 0.5 %."""
    lut = luts["two-projector"]
    ok = lut.usable
    span = np.zeros(lut.h0.shape)
    span[ok] = (LUT_SAMPLES - 1) / lut.inv_dh[ok].astype(np.float64)
    rng = np.random.default_rng(3)
    # inside, near both ends and outside the table, and pixels without a ratio
    t = rng.uniform(-0.05, 1.05, lut.h0.shape)
    grid = np.where(ok & (rng.random(lut.h0.shape) > 0.2), lut.h0 + t * span, np.nan)
    grid = grid.astype(np.float32)
    z, slope = depth_and_slope(lut, grid)
    assert z.dtype == slope.dtype == np.float32
    assert np.array_equal(z, lookup_depth(lut, grid), equal_nan=True)
    assert np.array_equal(np.isfinite(z), np.isfinite(slope))
    eps = 1e-3
    fd = np.abs(lookup_depth(lut, grid.astype(np.float64) + eps)
                - lookup_depth(lut, grid.astype(np.float64) - eps)) / (2 * eps)  # fmt: skip
    both = np.isfinite(fd) & np.isfinite(slope)
    assert np.count_nonzero(both) > 0.5 * np.count_nonzero(ok)
    rel = np.abs(slope[both] - fd[both]) / fd[both]
    assert np.percentile(rel, 99) < 0.005, np.percentile(rel, [50, 99, 100])


# ------------------------------------------------------------------ independent h


def _fd_h_uniform(rig, rays_xy, z, rel=1e-6):
    """h from central differences of the projector column (project_to_projector) and pitch."""
    dz = rel * z
    logs = []
    for proj, pat in rig.patterns:
        assert pat.kind == "uniform"
        pts = lambda zz: np.concatenate([rays_xy * zz[:, None], zz[:, None]], axis=1)  # noqa: E731
        up = project_to_projector(proj, pts(z + dz))[:, 0]
        um = project_to_projector(proj, pts(z - dz))[:, 0]
        du = (up - um) / (2 * dz)
        logs.append(np.log(np.abs(du) / pat.pitch_px))
    return logs[0] - logs[1]


@pytest.mark.parametrize("name", ["two-projector", "two-projector-distorted"])
def test_h_matches_finite_differences_of_projector_columns(name, rigs):
    rig = rigs[name]
    rays = camera_rays(rig.camera, STRIDE)
    rng = np.random.default_rng(5)
    gh, gw = rays.shape[:2]
    ii, jj = rng.integers(0, gh, 500), rng.integers(0, gw, 500)
    xy = np.ascontiguousarray(rays[ii, jj, :2])
    z = rng.uniform(0.5, 1.0, 500)
    h = h_function(rig, xy, z)
    ref = _fd_h_uniform(rig, xy, z)
    diff = np.abs(h - ref)
    print(f"\n{name}: |h - h_fd| max {diff.max():.2e} (h spans {np.ptp(h):.3f})")
    assert diff.max() < 1e-5
    # and h really changes with depth here (otherwise the check above is vacuous)
    assert np.ptp(h) > 0.1


def test_single_projector_h_is_log_ratio_of_line_spacings(rigs):
    """exp2 pair: h = log(P2(u)/P1(u)), P from the actual line centres (symmetric differences)."""
    rig = rigs["single-projector"]
    proj = rig.projectors[0]
    (_, p1), (_, p2) = rig.patterns
    rays = camera_rays(rig.camera, STRIDE)
    rng = np.random.default_rng(9)
    gh, gw = rays.shape[:2]
    ii, jj = rng.integers(0, gh, 400), rng.integers(0, gw, 400)
    xy = np.ascontiguousarray(rays[ii, jj, :2])
    z = rng.uniform(0.5, 1.0, 400)
    u = project_to_projector(proj, np.concatenate([xy * z[:, None], z[:, None]], axis=1))[:, 0]

    def pitch(pat):
        c = line_centres(pat, proj.width)
        sym = (c[2:] - c[:-2]) / 2  # exact local pitch at the inner lines (linear in u)
        slope, icpt = np.polyfit(c[1:-1], sym, 1)
        assert np.allclose(slope * c[1:-1] + icpt, sym, rtol=1e-9)
        return slope * u + icpt

    ref = np.log(pitch(p2) / pitch(p1))
    h = h_function(rig, xy, z)
    assert np.max(np.abs(h - ref)) < 1e-9


# ------------------------------------------------------------------ memory and cache


def test_full_resolution_lut_fits_in_200_mb(luts):
    lut = luts["two-projector"]
    per_pixel = lut.h0.dtype.itemsize + lut.inv_dh.dtype.itemsize
    per_pixel += LUT_SAMPLES * lut.table.dtype.itemsize
    # the formula is what the object really holds
    assert lut.nbytes == per_pixel * lut.h0.size
    total = 1600 * 1200 * per_pixel  # stride 1
    print(f"\nLUT at 1600x1200 stride 1: {per_pixel} B/pixel, {total / 1e6:.1f} MB")
    assert total <= 200e6


def test_lut_cache_round_trip_and_key(monkeypatch, tmp_path, rigs):
    monkeypatch.setenv("LIGHTFLOW_CACHE", str(tmp_path))
    rig = rigs["two-projector"].scaled(0.5)
    first = load_or_build_lut(rig, STRIDE, RANGE)
    files = sorted(tmp_path.glob("*.npz"))
    assert len(files) == 1 and files[0].stat().st_size > 0

    def no_build(*args, **kwargs):
        raise AssertionError("LUT rebuilt although it is cached")

    with monkeypatch.context() as m:
        m.setattr(depth_model, "build_lut", no_build)
        second = load_or_build_lut(rig, STRIDE, RANGE)
    for field in ("h0", "inv_dh", "table"):
        a, b = getattr(first, field), getattr(second, field)
        assert a.dtype == b.dtype and a.shape == b.shape
        np.testing.assert_array_equal(a, b)
    assert second.stride == STRIDE

    # a changed rig (projector moved by 5 mm) gets its own entry
    d = copy.deepcopy(rig.to_dict())
    d["projectors"][0]["t"][0] += 0.005
    moved = rig_from_dict(d, "moved")
    third = load_or_build_lut(moved, STRIDE, RANGE)
    files2 = sorted(tmp_path.glob("*.npz"))
    assert len(files2) == 2
    assert files[0] in files2
    assert not np.array_equal(third.table, first.table, equal_nan=True)


# ------------------------------------------------------------------ degenerate rig


def parallel_rig_dict() -> dict:
    """Two projectors side by side at the camera's depth, optical axes parallel to it."""
    d = rig_dict("two-projector")
    eye = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    for p, cx in zip(d["projectors"], (-0.2, 0.2), strict=True):
        p["R"] = eye
        p["t"] = [-cx, 0.0, 0.0]  # X_proj = X_cam + t: centre at (cx, 0, 0)
    return d


def test_parallel_projectors_have_flat_h():
    rig = rig_from_dict(parallel_rig_dict(), "parallel")
    rays = camera_rays(rig.camera, 64)
    xy = np.ascontiguousarray(rays[..., :2].reshape(-1, 2))
    h_near = h_function(rig, xy, np.full(len(xy), 0.5))
    h_far = h_function(rig, xy, np.full(len(xy), 1.0))
    assert np.all(np.isfinite(h_near))
    assert np.max(np.abs(h_far - h_near)) < 1e-9


def test_parallel_projectors_are_refused_by_the_pipeline():
    rig = rig_from_dict(parallel_rig_dict(), "parallel").scaled(0.5)
    with pytest.raises(ConfigError, match="parallel") as info:
        DepthPipeline(rig, PipelineConfig(stride=4))
    print(f"\nparallel rig: {info.value}")
