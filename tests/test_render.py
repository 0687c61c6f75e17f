"""The fast renderer against its slow exact (Monte Carlo) form, and its closed-form integrals."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lightflow.app.rig import resolve_rig
from lightflow.drivers.render import box_erf_mean
from lightflow.drivers.scenes import get_scene
from lightflow.drivers.synthetic import SceneRenderer, SensorModel

SCALE = 0.08  # 128x96 camera: small enough for many reference samples


@pytest.mark.parametrize("widths", [(), (0.7,), (0.7, -0.3), (2.5, 0.4, -0.9)])
@pytest.mark.parametrize("lo", [-2.0, 0.1, 1.3])
def test_box_erf_matches_quadrature(widths, lo):
    k = 1.0 / (math.sqrt(2) * 0.6)
    n = len(widths)
    w = np.array(list(widths) + [0.0] * (3 - n))
    # midpoint rule on a fine grid of the unit cube
    g = (np.arange(64) + 0.5) / 64
    grids = np.meshgrid(*([g] * n), indexing="ij") if n else []
    u = lo + sum(wd * s for wd, s in zip(widths, grids, strict=True)) if n else np.array(lo)
    want = np.mean([math.erf(k * x) for x in np.ravel(u)])
    assert box_erf_mean(k, lo, w, n) == pytest.approx(want, abs=2e-4)


@pytest.fixture(scope="module", params=["board", "fan", "ball"])
def pair(request):
    """Fast image, slow 32-sample image and a 512-sample reference, without lens blur."""
    scene = get_scene(request.param)
    rig = resolve_rig("two-projector").scaled(SCALE)
    sensor = SensorModel(lens_blur_px=0.0)
    t0 = 0.05
    fast_r = SceneRenderer(rig, scene, sensor)
    fast = fast_r.radiance(t0, scene.exposure_s)
    mc = fast_r.last_mc_fraction
    slow = fast_r.radiance(t0, scene.exposure_s, exact=True)
    ref_r = SceneRenderer(rig, scene, SensorModel(lens_blur_px=0.0, samples=512))
    ref = ref_r.radiance(t0, scene.exposure_s, exact=True)
    return request.param, fast, slow, ref, mc


def test_fast_form_agrees_with_exact_form(pair):
    name, fast, slow, ref, mc = pair
    assert ref.max() > 60  # lit lines, not a dark frame
    err_fast = np.abs(fast - ref)
    err_slow = np.abs(slow - ref)
    # the fast form integrates smooth pixels exactly: it is closer to the
    # well-converged reference than the 32-sample form it replaces
    assert err_fast.mean() < 0.7 * err_slow.mean(), name
    assert err_fast.mean() < 0.5, name  # DN, of lines up to ~200 DN
    assert abs((fast - ref).mean()) < 0.05, name  # no bias
    assert mc < 0.5, name  # most pixels take the exact path
