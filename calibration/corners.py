"""Board corners in the camera image and, through local homographies, in each projector.

The projector cannot see, so its view of a board corner is computed from the
decoded Gray code (Moreno & Taubin 2012, "Simple, accurate, and robust
projector-camera calibration"): in a window around the corner, fit a
homography from camera pixels to decoded projector pixels, robustly, and map
the sub-pixel camera corner through it.  The quantised decoding averages out
over the window, giving sub-pixel projector corners.
"""

from __future__ import annotations

import cv2
import numpy as np

from .session import Board

#: window side in camera pixels at 1600 px image width (Moreno & Taubin use 47)
WINDOW_AT_1600 = 47


def find_board_corners(image: np.ndarray, board: Board) -> np.ndarray | None:
    """Sub-pixel inner corners of the checkerboard in a grey image.

    Parameters
    ----------
    image : numpy.ndarray
        ``(h, w)`` grey image on an 8-bit scale (any dtype).
    board : Board

    Returns
    -------
    numpy.ndarray or None
        ``(columns * rows, 2)`` float32 corners in OpenCV order, or None if the
        board is not found.
    """
    img8 = np.clip(np.asarray(image, np.float32), 0, 255).round().astype(np.uint8)
    # stretch contrast so that dim sessions still detect
    lo, hi = np.percentile(img8, (1, 99.5))
    if hi - lo > 10:
        img8 = np.clip((img8.astype(np.float32) - lo) * (255.0 / (hi - lo)), 0, 255)
        img8 = img8.astype(np.uint8)
    size = board.pattern_size
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    # classic detector on a reduced image for speed, then refine at full size
    scale = max(1, round(img8.shape[1] / 800))
    small = cv2.resize(img8, None, fx=1 / scale, fy=1 / scale, interpolation=cv2.INTER_AREA)
    ok, corners = cv2.findChessboardCorners(small, size, flags=flags)
    if ok:
        corners = (corners.reshape(-1, 2) + 0.5) * scale - 0.5
    else:
        ok, corners = cv2.findChessboardCornersSB(img8, size, flags=cv2.CALIB_CB_EXHAUSTIVE)
        if not ok:
            return None
        corners = corners.reshape(-1, 2)
    # refinement window: about a third of a square, at least 3 px
    sq = _square_px(corners.reshape(size[1], size[0], 2))
    win = int(np.clip(sq / 3, 3, 15))
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    pts = np.ascontiguousarray(corners.reshape(-1, 1, 2), np.float32)
    cv2.cornerSubPix(img8, pts, (win, win), (-1, -1), crit)
    pts = np.ascontiguousarray(pts.reshape(-1, 2), np.float32)
    return _canonical_order(pts, size)


def _square_px(grid: np.ndarray) -> float:
    dx = np.linalg.norm(np.diff(grid, axis=1), axis=-1)
    dy = np.linalg.norm(np.diff(grid, axis=0), axis=-1)
    return float(min(np.median(dx), np.median(dy)))


def _canonical_order(corners: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Reverse the corner order if it starts at the bottom of the image.

    OpenCV may return a 180-degree rotated ordering of a board; a consistent
    ordering keeps the board frames of different poses alike (nicer reports).
    """
    if corners[0, 1] > corners[-1, 1]:
        return np.ascontiguousarray(corners[::-1])
    return corners


def window_size(image_width: int) -> int:
    """Odd window side for local homographies, scaled with the camera resolution."""
    w = round(WINDOW_AT_1600 * image_width / 1600)
    return max(11, w | 1)


def corners_to_projector(
    corners: np.ndarray,
    proj: np.ndarray,
    valid: np.ndarray,
    window: int,
    min_fraction: float = 0.3,
    ransac_px: float = 1.5,
) -> tuple[np.ndarray, np.ndarray]:
    """Map camera corners to projector pixels through local homographies.

    Parameters
    ----------
    corners : numpy.ndarray
        ``(n, 2)`` sub-pixel camera corners.
    proj : numpy.ndarray
        ``(h, w, 2)`` decoded projector ``(x, y)`` per camera pixel.
    valid : numpy.ndarray
        ``(h, w)`` bool decoding mask.
    window : int
        Odd window side in camera pixels.
    min_fraction : float
        Minimum fraction of valid pixels in a window.
    ransac_px : float
        RANSAC inlier threshold in projector pixels.

    Returns
    -------
    points : numpy.ndarray
        ``(n, 2)`` float32 projector coordinates (NaN where not found).
    ok : numpy.ndarray
        ``(n,)`` bool.
    """
    h, w = valid.shape
    half = window // 2
    n = len(corners)
    out = np.full((n, 2), np.nan, np.float32)
    ok = np.zeros(n, bool)
    offs = np.arange(-half, half + 1)
    for i, (cx, cy) in enumerate(np.asarray(corners, np.float64)):
        x0, y0 = int(round(cx)), int(round(cy))
        if x0 - half < 0 or y0 - half < 0 or x0 + half >= w or y0 + half >= h:
            continue
        m = valid[y0 - half : y0 + half + 1, x0 - half : x0 + half + 1]
        if m.mean() < min_fraction:
            continue
        gx, gy = np.meshgrid(offs + x0 - cx, offs + y0 - cy)  # relative to the corner
        src = np.stack([gx[m], gy[m]], axis=1)
        dst = proj[y0 - half : y0 + half + 1, x0 - half : x0 + half + 1][m].astype(np.float64)
        H, inl = cv2.findHomography(src, dst, cv2.RANSAC, ransac_px, maxIters=2000,
                                    confidence=0.999)
        if H is None or inl is None or inl.sum() < 0.5 * len(src):
            continue
        inl = inl.ravel().astype(bool)
        # final least-squares fit on the inliers (findHomography refines with LM)
        H2, _ = cv2.findHomography(src[inl], dst[inl], 0)
        if H2 is not None:
            H = H2
        if abs(H[2, 2]) < 1e-12:
            continue
        out[i] = H[:2, 2] / H[2, 2]  # the corner is the origin of src
        ok[i] = True
    return out, ok
