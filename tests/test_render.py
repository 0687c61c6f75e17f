"""The fast renderer (exact in time, adaptive knots) against its slow Monte Carlo form."""

from __future__ import annotations

import numpy as np
import pytest

from lightflow.app.rig import resolve_rig
from lightflow.drivers.render import image_motion_px, knot_depths, line_light_tables
from lightflow.drivers.scenes import get_scene
from lightflow.drivers.synthetic import SceneRenderer, SensorModel

SCALE = 0.1  # 160 x 120


def test_line_light_table_is_the_exact_integral():
    foot = np.array([[10.0, 20.0], [40.0, 41.0]])
    tab = line_light_tables(foot, 0.6, 100)
    u = tab[3, 0] + np.arange(tab.shape[1]) * tab[3, 1]
    # G is the antiderivative of L: 0 far left, the lit width far right
    assert tab[2, 0] == pytest.approx(0.0, abs=1e-12)
    assert tab[2, -1] == pytest.approx(11.0, abs=1e-9)
    assert np.abs(np.gradient(tab[2], u) - tab[0]).max() < 2e-3
    # the plateau of a wide line is 1
    assert tab[0, np.argmin(np.abs(u - 15.0))] == pytest.approx(1.0, abs=1e-6)


def test_knot_depths_follow_image_motion():
    assert knot_depths(0.0) == (0, 1)
    dmin, dmax = knot_depths(64.0)
    # edges resolved to 0.25 px, smooth motion knotted at least every 16 px
    assert 64.0 / 2**dmax <= 0.25 and 64.0 / 2 ** (dmin + 1) <= 16.0
    prims = get_scene("board").primitives(0.1)
    assert image_motion_px(prims, 0.1, 0.0, 1800.0, 1800.0) == 0.0
    assert image_motion_px(prims, 0.1, 0.02, 1800.0, 1800.0) > 1.0


# measured (1024 samples): board 0.32 / 1.9 DN, ball 0.04 / 0.9, fan 0.75 / 8.6 (thin
# lines on the far wall at this scale), two balls 0.06 / 1.4; the rest is the
# reference's own sampling noise and the 2 x 2 pixel-area rule
@pytest.mark.parametrize(
    ("scene", "rig", "t0", "mean_abs", "p99"),
    [("board", "two-projector", 0.13, 0.45, 2.5), ("ball", "two-projector", 0.05, 0.1, 1.5),
     ("fan", "two-projector-distorted", 0.03, 1.0, 10.0),
     ("two-balls", "single-projector", 0.1, 0.1, 2.0)],
)  # fmt: skip
def test_fast_form_matches_slow_exact_form(scene, rig, t0, mean_abs, p99):
    r = resolve_rig(rig).scaled(SCALE)
    sc = get_scene(scene)
    fast = SceneRenderer(r, sc, SensorModel()).radiance(t0, sc.exposure_s)
    slow = SceneRenderer(r, sc, SensorModel(method="sampled", samples=1024)).radiance(
        t0, sc.exposure_s
    )
    diff = np.abs(fast - slow)
    assert slow.max() > 50  # lit lines, not an empty frame
    assert abs(float(fast.mean() - slow.mean())) < 0.05  # no bias: the same light in total
    assert diff.mean() < mean_abs
    assert np.percentile(diff, 99) < p99
