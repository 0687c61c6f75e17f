"""The core's one lens model against OpenCV's own projection and undistortion."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from lightflow.app.core.geometry import (
    camera_rays,
    lens_coefficients,
    lens_distort,
    lens_distort_derivative,
    project_points,
    project_to_projector,
    undistort_pixels,
)
from lightflow.app.core.rig import resolve_rig


def _whole_image(width, height, step=7):
    ys, xs = np.mgrid[0:height:step, 0:width:step]
    return np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)


@pytest.mark.parametrize("rig_name", ["two-projector-distorted", "two-projector"])
def test_core_lens_agrees_with_opencv_over_every_device(rig_name):
    rig = resolve_rig(rig_name)
    devices = [rig.camera, *rig.projectors]
    assert rig_name != "two-projector-distorted" or all(np.any(d.dist) for d in devices)
    for dev in devices:
        pix = _whole_image(dev.width, dev.height)
        # rays through every 7th pixel of the whole image, at several depths
        xy = cv2.undistortPointsIter(
            pix.reshape(-1, 1, 2), dev.K, dev.dist, None, None,
            (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14),
        ).reshape(-1, 2)  # fmt: skip
        z = np.random.default_rng(0).uniform(0.3, 3.0, len(xy))
        pts = np.column_stack([xy * z[:, None], z])
        ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), dev.K, dev.dist)
        ours = project_points(dev.K, dev.dist, pts)
        assert np.abs(ours - ref.reshape(-1, 2)).max() < 1e-6
        # and the undistortion round trip: pixel -> ray -> the same pixel
        xy = undistort_pixels(dev.K, dev.dist, pix)
        back = project_points(dev.K, dev.dist, np.column_stack([xy, np.ones(len(pix))]))
        assert np.abs(back - pix).max() < 1e-6


def test_camera_rays_project_back_onto_their_pixel_centres_with_opencv():
    cam = resolve_rig("two-projector-distorted").camera
    for stride in (1, 4):
        rays = camera_rays(cam, stride)
        back, _ = cv2.projectPoints(rays.reshape(-1, 3), np.zeros(3), np.zeros(3), cam.K, cam.dist)
        gh, gw = rays.shape[:2]
        off = (stride - 1) / 2
        ys, xs = np.mgrid[0:gh, 0:gw] * stride + off
        want = np.stack([xs.ravel(), ys.ravel()], 1)
        assert np.abs(back.reshape(-1, 2) - want).max() < 1e-6


def test_projector_projection_agrees_with_opencv_in_the_camera_frame():
    rig = resolve_rig("two-projector-distorted")
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(-0.4, 0.4, (4000, 2)), rng.uniform(0.5, 1.2, 4000)])
    for p in rig.projectors:
        rvec, _ = cv2.Rodrigues(np.asarray(p.R, np.float64))
        ref, _ = cv2.projectPoints(pts, rvec, np.asarray(p.t, np.float64), p.K, p.dist)
        ref = ref.reshape(-1, 2)
        inside = (ref[:, 0] > -50) & (ref[:, 0] < p.width + 50)
        inside &= (ref[:, 1] > -50) & (ref[:, 1] < p.height + 50)
        assert inside.sum() > 500
        ours = project_to_projector(p, pts)
        assert np.abs(ours[inside] - ref[inside]).max() < 1e-6


DIST12 = np.array([-0.2, 0.05, 1e-3, -2e-3, 0.01, 0.1, -0.02, 0.005, 1e-3, -5e-4, 2e-3, 1e-4])
#: with a tilted sensor (tau_x, tau_y in radians)
DIST14 = np.concatenate([DIST12, [0.02, -0.015]])


@pytest.mark.parametrize("dist", [DIST12, DIST14], ids=["12", "14-tilted"])
def test_rational_thin_prism_and_tilt_terms_agree_with_opencv(dist):
    # OpenCV's model has no skew: projectPoints ignores K[0, 1]
    K = np.array([[900.0, 0.0, 640.0], [0.0, 910.0, 360.0], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(1)
    pts = np.column_stack([rng.uniform(-0.6, 0.6, (2000, 2)), np.ones(2000)])
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, dist)
    assert np.abs(project_points(K, dist, pts) - ref.reshape(-1, 2)).max() < 1e-6


@pytest.mark.parametrize("dist", [np.zeros(5), DIST12, DIST14], ids=["none", "12", "14-tilted"])
def test_undistortion_round_trip_with_skew(dist):
    # the rig format allows a skew s = K[0, 1]; projection and undistortion must both apply it
    K = np.array([[900.0, 2.5, 640.0], [0.0, 910.0, 360.0], [0.0, 0.0, 1.0]])
    pix = _whole_image(1280, 720, 11)
    xy = undistort_pixels(K, dist, pix)
    back = project_points(K, dist, np.column_stack([xy, np.ones(len(xy))]))
    assert np.abs(back - pix).max() < 1e-6


@pytest.mark.parametrize("dist", [DIST12, DIST14], ids=["12", "14-tilted"])
def test_lens_derivative_matches_finite_differences(dist):
    d = lens_coefficients(dist)
    rng = np.random.default_rng(2)
    for x, y, dx, dy in rng.uniform(-0.5, 0.5, (50, 4)):
        xd, yd, dxd, dyd = lens_distort_derivative(d, x, y, dx, dy)
        assert (xd, yd) == lens_distort(d, x, y)
        e = 1e-6
        xp, yp = lens_distort(d, x + e * dx, y + e * dy)
        xm, ym = lens_distort(d, x - e * dx, y - e * dy)
        assert dxd == pytest.approx((xp - xm) / (2 * e), abs=1e-8)
        assert dyd == pytest.approx((yp - ym) / (2 * e), abs=1e-8)


@pytest.mark.parametrize("strong", [None, DIST12, DIST14], ids=["rig", "12", "14-tilted"])
def test_simulator_projection_and_core_lens_agree_over_the_panel(strong):
    # the simulator tabulates cv2.projectPoints; the core evaluates its own model
    from lightflow.drivers.sim.render import lens_table, pack_projector, project_to_projector

    rig = resolve_rig("two-projector-distorted")
    rng = np.random.default_rng(4)
    for p in rig.projectors:
        dist = p.dist if strong is None else strong
        header, _ = lens_table(p.K, dist, p.width, p.height)
        assert header[4] > 0  # a table, not the pinhole shortcut
        # points whose projector pixels cover the whole panel
        pix = np.column_stack([rng.uniform(-0.5, p.width - 0.5, 20000),
                               rng.uniform(-0.5, p.height - 0.5, 20000)])  # fmt: skip
        xy = undistort_pixels(p.K, dist, pix)
        z = rng.uniform(0.3, 3.0, len(xy))
        pts_proj = np.column_stack([xy * z[:, None], z])
        pts_cam = (pts_proj - p.t) @ np.asarray(p.R)  # back into the camera frame
        sim = project_to_projector(pack_projector(p.R, p.t, p.K, dist, p.width, p.height), pts_cam)
        core = project_points(p.K, dist, pts_proj)
        assert np.abs(core - pix).max() < 1e-6
        assert np.abs(sim - pix).max() < 1e-6
