"""Gray-code sequence, decoding and local-homography corner mapping."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from lightflow.calibration.corners import corners_to_projector, window_size
from lightflow.calibration.graycode import (
    bit_counts,
    decode_graycode,
    frame_count,
    frame_labels,
    graycode_images,
)


def test_sequence_layout_matches_formats_md():
    w, h = 100, 60
    assert bit_counts(w, h) == (7, 6)
    assert frame_count(w, h) == 2 + 2 * (7 + 6)
    frames = list(graycode_images(w, h))
    assert len(frames) == 28
    assert all(f.shape == (h, w) and f.dtype == np.uint8 for f in frames)
    assert np.all(frames[0] == 255) and np.all(frames[1] == 0)
    x = np.arange(w)
    g = x ^ (x >> 1)
    # column bit 6 is frame 2, its inverse frame 3; bit 0 is frame 14
    np.testing.assert_array_equal(frames[2][5] == 255, ((g >> 6) & 1) == 1)
    np.testing.assert_array_equal(frames[3], 255 - frames[2])
    np.testing.assert_array_equal(frames[14][0] == 255, (g & 1) == 1)
    y = np.arange(h)
    gy = y ^ (y >> 1)
    np.testing.assert_array_equal(frames[16][:, 7] == 255, ((gy >> 5) & 1) == 1)
    np.testing.assert_array_equal(frames[16][:, 0], frames[16][:, 99])
    assert frame_labels(w, h)[3] == "column bit 6 inverse"
    assert frame_labels(w, h)[-1] == "row bit 0 inverse"


def _render_flat_warp(w, h, cam_w, cam_h, to_proj):
    """Camera frames of a flat scene where camera pixel (u, v) sees projector to_proj(u, v)."""
    u, v = np.meshgrid(np.arange(cam_w, dtype=float), np.arange(cam_h, dtype=float))
    px, py = to_proj(u, v)
    ix, iy = np.rint(px).astype(int), np.rint(py).astype(int)
    inside = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
    frames = []
    for pat in graycode_images(w, h):
        lit = np.zeros((cam_h, cam_w))
        lit[inside] = pat[iy[inside], ix[inside]] / 255.0
        frames.append(20 + 180 * lit)
    return frames, ix, iy, inside


def test_decode_exact_on_flat_warp():
    w, h = 100, 60
    frames, ix, iy, inside = _render_flat_warp(
        w, h, 160, 120, lambda u, v: (0.7 * u - 5.3 + 0.05 * v, 0.55 * v - 3.2))
    dec = decode_graycode(frames, w, h)
    np.testing.assert_array_equal(dec.valid, inside)
    np.testing.assert_array_equal(dec.proj[inside][:, 0], ix[inside])
    np.testing.assert_array_equal(dec.proj[inside][:, 1], iy[inside])


def test_decode_rejects_shadow_and_wrong_count():
    w, h = 32, 16
    frames = [np.full((10, 10), 30.0)] * frame_count(w, h)  # no contrast anywhere
    assert not decode_graycode(frames, w, h).valid.any()
    with pytest.raises(ValueError, match="expected 20 frames"):
        decode_graycode(frames[:-1], w, h)


def test_local_homography_maps_corner_exactly():
    H = np.array([[0.8, 0.05, 30.0], [-0.03, 0.75, 12.0], [2e-4, -1e-4, 1.0]])
    u, v = np.meshgrid(np.arange(200, dtype=np.float64), np.arange(150, dtype=np.float64))
    pts = cv2.perspectiveTransform(np.stack([u, v], -1).reshape(-1, 1, 2), H).reshape(150, 200, 2)
    corners = np.array([[50.3, 40.7], [120.25, 90.5], [100.0, 75.0]])
    truth = cv2.perspectiveTransform(corners.reshape(-1, 1, 2), H).reshape(-1, 2)
    valid = np.ones((150, 200), bool)
    out, ok = corners_to_projector(corners, pts.astype(np.float32), valid, 21)
    assert ok.all()
    np.testing.assert_allclose(out, truth, atol=1e-3)
    # quantised decoding (integer projector pixels) still gives sub-pixel corners
    out_q, ok_q = corners_to_projector(corners, np.rint(pts).astype(np.float32), valid, 31)
    assert ok_q.all()
    assert np.abs(out_q - truth).max() < 0.05


def test_local_homography_skips_unlit_and_border_corners():
    proj = np.zeros((100, 100, 2), np.float32)
    valid = np.zeros((100, 100), bool)
    out, ok = corners_to_projector(np.array([[50.0, 50.0], [2.0, 2.0]]), proj, valid, 21)
    assert not ok.any() and np.isnan(out).all()
    assert window_size(1600) == 47 and window_size(640) == 19
