"""The fast renderer against its slow exact (Monte Carlo) form, and its closed-form integrals."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lightflow.app.core.rig import resolve_rig
from lightflow.drivers.sim.render import box_erf_mean
from lightflow.drivers.sim.scenes import get_scene
from lightflow.drivers.sim.synthetic import SceneRenderer, SensorModel

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


SCALE_SIM = 0.1  # 160x120 for the scene and physics checks below

@pytest.mark.parametrize(
    ("scene", "z_lo", "z_hi"),
    [("ball-toward", 0.45, 0.95), ("ball-away", 0.55, 0.95), ("diagonal-board", 0.45, 1.0),
     ("newspaper-board", 0.6, 0.9), ("fan-1ms", 0.6, 1.06)],
)  # fmt: skip
def test_paper_scenes_have_ground_truth(scene, z_lo, z_hi):
    r = resolve_rig("two-projector").scaled(SCALE_SIM)
    sc = get_scene(scene)
    renderer = SceneRenderer(r, sc, SensorModel())
    for t in (0.05, 0.2):
        truth = renderer.truth(t + sc.exposure_s / 2)
        moving = truth.object_id >= 2
        assert moving.mean() > 0.02
        assert z_lo <= np.nanmin(truth.depth[moving]) <= np.nanmax(truth.depth[moving]) <= z_hi
        assert renderer.radiance(t, sc.exposure_s).max() > 30


def test_ball_toward_comes_closer():
    r = resolve_rig("two-projector").scaled(SCALE_SIM)
    renderer = SceneRenderer(r, get_scene("ball-toward"), SensorModel())
    near = [np.nanmin(renderer.truth(t).depth) for t in (0.02, 0.12, 0.22)]
    assert near[0] > near[1] > near[2]


@pytest.mark.parametrize("rig_name", ["two-projector-distorted", "single-projector"])
def test_projection_agrees_with_opencv(rig_name):
    import cv2

    from lightflow.drivers.sim.render import project_to_projector
    from lightflow.drivers.sim.synthetic import camera_rays_cv, pack_projectors

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
    from lightflow.drivers.sim.synthetic import disk_kernel, lens_blur

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
    r = resolve_rig("two-projector").scaled(SCALE_SIM)
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


def test_frames_rendered_ahead_are_the_same_frames():
    from lightflow.drivers.sim.synthetic import SyntheticCamera

    rig = resolve_rig("two-projector").scaled(SCALE)
    plain = SyntheticCamera(rig, "ball-wall", frames=3, fps=24)
    with plain:
        want = list(plain.frames())
    ahead = SyntheticCamera(rig, "ball-wall", frames=3, fps=24)
    assert ahead.render_ahead(2, threads=1) == 2
    assert ahead.frames_ahead == 2
    with ahead:
        got = list(ahead.frames())
    assert [f.index for f in got] == [0, 1, 2]
    for a, b in zip(want, got, strict=True):
        assert np.array_equal(a.image, b.image)  # same noise draws, in the same order
        assert np.array_equal(a.extras["truth"].depth, b.extras["truth"].depth, equal_nan=True)
    assert ahead.render_ahead(5) == 3  # a finite scene ends
