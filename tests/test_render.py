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


@pytest.mark.parametrize(
    ("scene", "z_lo", "z_hi"),
    [("ball-toward", 0.45, 0.95), ("ball-away", 0.55, 0.95), ("diagonal-board", 0.45, 1.0),
     ("newspaper-board", 0.6, 0.9), ("fan-1ms", 0.6, 1.06)],
)  # fmt: skip
def test_paper_scenes_have_ground_truth(scene, z_lo, z_hi):
    r = resolve_rig("two-projector").scaled(SCALE)
    sc = get_scene(scene)
    renderer = SceneRenderer(r, sc, SensorModel())
    for t in (0.05, 0.2):
        truth = renderer.truth(t + sc.exposure_s / 2)
        moving = truth.object_id >= 2
        assert moving.mean() > 0.02
        assert z_lo <= np.nanmin(truth.depth[moving]) <= np.nanmax(truth.depth[moving]) <= z_hi
        assert renderer.radiance(t, sc.exposure_s).max() > 30


def test_ball_toward_comes_closer():
    r = resolve_rig("two-projector").scaled(SCALE)
    renderer = SceneRenderer(r, get_scene("ball-toward"), SensorModel())
    near = [np.nanmin(renderer.truth(t).depth) for t in (0.02, 0.12, 0.22)]
    assert near[0] > near[1] > near[2]


@pytest.mark.parametrize("rig_name", ["two-projector-distorted", "single-projector"])
def test_projection_agrees_with_opencv(rig_name):
    import cv2

    from lightflow.drivers.render import project_to_projector
    from lightflow.drivers.synthetic import camera_rays_cv, pack_projectors

    rig = resolve_rig(rig_name)
    cam = rig.camera
    # camera rays from OpenCV's undistortion reproject onto their pixels
    rays = camera_rays_cv(cam.K, cam.dist, cam.width, cam.height)[::37, ::41].reshape(-1, 3)
    back, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    ys, xs = np.mgrid[0 : cam.height : 37, 0 : cam.width : 41]
    assert np.abs(back.reshape(-1, 2) - np.stack([xs.ravel(), ys.ravel()], 1)).max() < 1e-6
    # the kernel's projector model is OpenCV's, over the whole panel
    rng = np.random.default_rng(1)
    pts = rays * rng.uniform(0.5, 1.0, (len(rays), 1))
    for q, p in enumerate(rig.projectors):
        ours = project_to_projector(pack_projectors(rig)[q], pts)
        rvec, _ = cv2.Rodrigues(np.asarray(p.R, np.float64))
        ref, _ = cv2.projectPoints(pts, rvec, np.asarray(p.t, np.float64), p.K, p.dist)
        inside = (np.abs(ours[:, 0] - p.width / 2) < p.width) & (
            np.abs(ours[:, 1] - p.height / 2) < p.height
        )
        assert inside.sum() > 100
        assert np.abs(ours[inside] - ref.reshape(-1, 2)[inside]).max() < 1e-6


def test_gamma_and_disk_blur_change_the_image():
    from lightflow.drivers.synthetic import disk_kernel, lens_blur

    k = disk_kernel(1.5)
    assert k.sum() == pytest.approx(1.0) and np.allclose(k, k.T) and np.allclose(k, k[::-1])
    img = np.zeros((31, 31, 3))
    img[15, 15] = 1.0
    disk = lens_blur(img, "disk", 1.5)
    gauss = lens_blur(img, "gauss", 1.5)
    assert disk[..., 0].sum() == pytest.approx(1.0)
    assert gauss[..., 0].sum() == pytest.approx(1.0, abs=1e-6)
    # a disc is flat inside its radius, a Gaussian is not
    assert disk[15, 15, 0] == pytest.approx(disk[15, 16, 0], rel=0.05)
    assert gauss[15, 15, 0] > 1.2 * gauss[15, 16, 0]  # exp(1 / (2 * 1.5**2)) = 1.25
    r = resolve_rig("two-projector").scaled(SCALE)
    sc = get_scene("board")
    lin = SceneRenderer(r, sc, SensorModel(read_noise_dn=0.0, electrons_per_dn=1e6))
    gam = SceneRenderer(r, sc, SensorModel(read_noise_dn=0.0, electrons_per_dn=1e6,
                                           camera_gamma=2.2))  # fmt: skip
    rad = lin.radiance(0.1, sc.exposure_s)
    a = lin.expose(rad, np.random.default_rng(0)).astype(float)
    b = gam.expose(rad, np.random.default_rng(0)).astype(float)
    mid = (a > 20) & (a < 120)
    expected = 255 * (a[mid] / 255) ** (1 / 2.2)
    assert np.abs(b[mid] - expected).max() < 1.5
