"""A plain reference implementation of the paper: the baseline of ``lightflow bench``.

Not used by the pipeline.  It exists so that the pipeline's speed can be
stated against something fixed: "N times faster than a straightforward
implementation of structured light flow", measured side by side in one run.

It follows the paper's description (Furukawa et al., section "light flow
estimation") and nothing more, written the way one would first write it:
NumPy, one image row at a time, in plain Python loops over rows.

- Every pattern has its own colour channel (no crosstalk correction).
- Per analysis row (the rows of the depth table's grid) the channel is
  binarised adaptively: above its moving average over a window of about two
  line intervals (measured per frame on a few rows).  Each run above the
  threshold is a band; its two ends are located with sub-pixel accuracy
  where the profile crosses the threshold (linear interpolation).  Band
  length ``dr`` = right - left crossing.
- Line interval ``B``: mean distance of a band's centre to its two
  neighbours.  Bands whose interval lies outside ``interval_limits`` times
  the row's median interval are outliers (boundaries, missing lines).
- Flow in line-index units ``dr / B``, interpolated linearly between band
  centres onto the grid columns (not across gaps wider than 1.6 intervals).
- ``log(flow_1 / flow_2)``, smoothed by a masked Gaussian, gives depth
  through the same depth table (:class:`~lightflow.app.core.depth_model.DepthLUT`)
  that the pipeline uses, interpolated linearly; the grid is resized
  bilinearly to the camera's size.

No line-width or blur model, no static-line test, no leak correction: its
depth is less accurate than the pipeline's, and it is not meant to be used.
It handles two-projector rigs with uniform patterns (the paper's first
setup).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .core.depth_model import DepthLUT, DepthRange, load_or_build_lut
from .core.errors import ConfigError
from .core.rig import CHANNEL_INDEX, Rig
from .recording import load_frame, read_recording


def row_flows(
    signal: np.ndarray,
    columns: np.ndarray,
    window_px: int = 61,
    interval_limits: tuple[float, float] = (0.7, 1.3),
) -> np.ndarray:
    """Flow ``dr / B`` (line-index units) of one image row, at the given columns.

    Parameters
    ----------
    signal : numpy.ndarray
        ``(W,)`` one row of one colour channel.
    columns : numpy.ndarray
        Image x of the grid columns to interpolate onto.
    window_px : int
        Window of the moving average that is the binarisation threshold.
    interval_limits : tuple of float
        Accepted intervals, as fractions of the row's median interval.

    Returns
    -------
    numpy.ndarray
        ``(len(columns),)`` flows; NaN where no band pair brackets the column.
    """
    s = signal.astype(np.float64)
    half = window_px // 2
    padded = np.pad(s, half, mode="reflect")
    thr = np.convolve(padded, np.full(window_px, 1.0 / window_px), mode="valid")
    above = s > thr
    step = np.diff(above.astype(np.int8))
    ups = np.flatnonzero(step == 1)  # crossing between j and j + 1, rising
    downs = np.flatnonzero(step == -1)  # falling
    out = np.full(len(columns), np.nan)
    if len(ups) == 0:
        return out
    downs = downs[downs > ups[0]]
    n = min(len(ups), len(downs))
    ups, downs = ups[:n], downs[:n]
    if n < 3:
        return out
    d = s - thr  # crosses zero between j and j + 1
    left = ups - d[ups] / (d[ups + 1] - d[ups])
    right = downs + d[downs] / (d[downs] - d[downs + 1])
    length = right - left
    centre = 0.5 * (left + right)
    interval = np.full(n, np.nan)
    interval[1:-1] = 0.5 * (centre[2:] - centre[:-2])
    median = np.nanmedian(interval)
    good = (interval > interval_limits[0] * median) & (interval < interval_limits[1] * median)
    if np.count_nonzero(good) < 2:
        return out
    c = centre[good]
    flow = length[good] / interval[good]
    iv = interval[good]
    out = np.interp(columns, c, flow, left=np.nan, right=np.nan)
    # no interpolation across a gap (an object boundary, lost bands)
    k = np.clip(np.searchsorted(c, columns), 1, len(c) - 1)
    wide = (c[k] - c[k - 1]) > 1.6 * np.maximum(iv[k], iv[k - 1])
    out[wide] = np.nan
    return out


def binarisation_window(channel: np.ndarray, rows: int = 9) -> int:
    """Two line intervals (odd, px): the median band spacing on a few rows, binarised wide."""
    h, w = channel.shape
    spacing = []
    for y in np.linspace(h // 4, 3 * h // 4, rows).astype(int):
        s = channel[y].astype(np.float64)
        wide = max(31, w // 12) | 1
        thr = np.convolve(
            np.pad(s, wide // 2, mode="reflect"), np.full(wide, 1.0 / wide), mode="valid"
        )
        ups = np.flatnonzero(np.diff((s > thr).astype(np.int8)) == 1)
        spacing.append(np.diff(ups))
    d = np.concatenate(spacing)
    return int(2 * np.median(d)) | 1 if d.size >= 10 else 61


def lut_depth(lut: DepthLUT, log_ratio: np.ndarray) -> np.ndarray:
    """Depth from the depth table by linear interpolation in h (NaN outside it)."""
    m = lut.table.shape[2]
    t = (log_ratio - lut.h0) * lut.inv_dh
    ok = np.isfinite(t) & (lut.inv_dh > 0) & (t >= 0) & (t <= m - 1)
    t = np.where(ok, t, 0.0)
    j = np.minimum(t.astype(np.int64), m - 2)
    f = t - j
    lo = np.take_along_axis(lut.table, j[..., None], axis=2)[..., 0]
    hi = np.take_along_axis(lut.table, j[..., None] + 1, axis=2)[..., 0]
    inv_z = lo + f * (hi - lo)
    return np.where(ok, 1.0 / inv_z, np.nan).astype(np.float32)


def reference_depth(
    image: np.ndarray, rig: Rig, lut: DepthLUT, window_px: int = 0, smoothing_px: float = 24.0
) -> np.ndarray:
    """Full-resolution depth (metres, NaN without estimate) of one frame, the plain way.

    Parameters
    ----------
    image : numpy.ndarray
        ``(H, W, 3)`` RGB frame.
    rig : Rig
        A two-projector rig with uniform patterns.
    lut : DepthLUT
        The depth table at the analysis stride.
    window_px : int
        Window of the adaptive binarisation; 0: two line intervals, measured
        per pattern on this frame (:func:`binarisation_window`).
    smoothing_px : float
        Gaussian sigma (camera px) of the masked smoothing of the log ratio.
    """
    if rig.single_projector or any(pat.kind != "uniform" for _, pat in rig.patterns):
        raise ConfigError("reference: needs a two-projector rig with uniform patterns")
    stride = lut.stride
    gh, gw = lut.h0.shape
    rows = np.arange(gh) * stride + (stride - 1) // 2
    columns = np.arange(gw) * stride + 0.5 * (stride - 1)
    flows = np.full((2, gh, gw), np.nan)
    for p, (_, pat) in enumerate(rig.patterns):
        channel = CHANNEL_INDEX[pat.channel]
        window = window_px or binarisation_window(image[..., channel])
        for i, y in enumerate(rows):
            flows[p, i] = row_flows(image[y, :, channel], columns, window)
    with np.errstate(invalid="ignore", divide="ignore"):
        log_ratio = np.log(flows[0] / flows[1])
    mask = np.isfinite(log_ratio)
    if smoothing_px > 0:
        sigma = smoothing_px / stride
        num = cv2.GaussianBlur(np.where(mask, log_ratio, 0.0), (0, 0), sigma)
        den = cv2.GaussianBlur(mask.astype(np.float64), (0, 0), sigma)
        with np.errstate(invalid="ignore", divide="ignore"):
            log_ratio = np.where(mask, num / den, np.nan)
    depth = lut_depth(lut, log_ratio)
    cam = rig.camera
    return cv2.resize(depth, (cam.width, cam.height), interpolation=cv2.INTER_LINEAR)


def reference_replay(
    rec: str | Path, out_dir: str | Path, lut: DepthLUT | None = None, stride: int = 4
) -> int:
    """Like ``lightflow replay REC --export-depth OUT``, one frame after the other.

    Decodes every frame, computes :func:`reference_depth` and writes
    ``OUT/<frame>.npy`` (float32).  Returns the number of frames written.
    """
    recording = read_recording(rec)
    rig = recording.rig
    if lut is None:
        lut = load_or_build_lut(rig, stride, DepthRange())
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for i, entry in enumerate(recording.frames):
        depth = reference_depth(load_frame(recording, i), rig, lut)
        np.save(out / f"{entry.stem}.npy", depth.astype(np.float32))
    return len(recording.frames)
