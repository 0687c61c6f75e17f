"""A small line-plot renderer on OpenCV (no matplotlib): axes, ticks, labels, legend.

Used by ``lightflow eval`` to draw depth error against exposure.  Images are
BGR uint8 arrays, as :func:`cv2.imwrite` expects.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from lightflow.app.errors import ConfigError

FONT = cv2.FONT_HERSHEY_SIMPLEX
#: a colour-blind-safe cycle (Okabe-Ito), BGR
COLOURS = (
    (178, 114, 0), (0, 94, 213), (115, 158, 0), (167, 121, 204), (233, 180, 86),
    (66, 228, 240), (0, 0, 0),
)  # fmt: skip
MARKERS = ("circle", "square", "triangle", "diamond")


@dataclass(frozen=True)
class Series:
    """One polyline of a plot.  NaN values are skipped (the line breaks there)."""

    label: str
    x: tuple[float, ...]
    y: tuple[float, ...]


def nice_ticks(lo: float, hi: float, target: int = 6) -> np.ndarray:
    """Round tick values (1, 2, 5 times a power of ten) covering ``[lo, hi]``.

    Returns about ``target`` ticks; the first is <= lo and the last >= hi.
    """
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError(f"nice_ticks: non-finite range {lo}, {hi}")
    if hi <= lo:
        pad = abs(lo) * 0.1 or 1.0
        lo, hi = lo - pad, hi + pad
    raw = (hi - lo) / max(target - 1, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw * (1 - 1e-9))
    start = math.floor(lo / step + 1e-9) * step
    stop = math.ceil(hi / step - 1e-9) * step
    n = round((stop - start) / step)
    return start + step * np.arange(n + 1)


def _fmt(v: float, step: float) -> str:
    decimals = max(0, -math.floor(math.log10(step) + 1e-9)) if step > 0 else 0
    if step > 0 and round(step / 10.0 ** math.floor(math.log10(step)), 6) == 2.5:
        decimals += 1
    return f"{v:.{decimals}f}"


def _text(img, text, org, scale=0.5, colour=(0, 0, 0), thickness=1, anchor="left"):
    (w, h), base = cv2.getTextSize(text, FONT, scale, thickness)
    x, y = org
    if anchor == "centre":
        x -= w // 2
    elif anchor == "right":
        x -= w
    cv2.putText(img, text, (int(x), int(y)), FONT, scale, colour, thickness, cv2.LINE_AA)
    return w, h + base


def _marker(img, centre, kind, colour, r=5):
    x, y = centre
    if kind == "circle":
        cv2.circle(img, centre, r, colour, -1, cv2.LINE_AA)
    elif kind == "square":
        cv2.rectangle(img, (x - r + 1, y - r + 1), (x + r - 1, y + r - 1), colour, -1)
    else:
        if kind == "triangle":
            pts = [(x, y - r), (x + r, y + r - 1), (x - r, y + r - 1)]
        else:
            pts = [(x, y - r), (x + r, y), (x, y + r), (x - r, y)]
        cv2.fillPoly(img, [np.array(pts, np.int32)], colour, cv2.LINE_AA)


def line_plot(
    series: list[Series],
    *,
    title: str = "",
    xlabel: str = "",
    ylabel: str = "",
    size: tuple[int, int] = (900, 560),
    y_from_zero: bool = True,
) -> np.ndarray:
    """Draw ``series`` as lines with markers on labelled axes.

    Parameters
    ----------
    series : list of Series
    title, xlabel, ylabel : str
    size : (int, int)
        Image width and height in pixels.
    y_from_zero : bool
        Start the y axis at 0 (errors), unless a value is negative.

    Returns
    -------
    numpy.ndarray
        ``(height, width, 3)`` BGR uint8 image.
    """
    width, height = size
    img = np.full((height, width, 3), 255, np.uint8)
    xs = np.array([v for s in series for v in s.x], dtype=np.float64)
    ys = np.array([v for s in series for v in s.y], dtype=np.float64)
    ok = np.isfinite(xs) & np.isfinite(ys)
    if not ok.any():
        xs, ys = np.array([0.0, 1.0]), np.array([0.0, 1.0])
        ok = np.ones(2, bool)
    # a little headroom so that markers do not sit on the frame
    xmin, xmax = float(xs[ok].min()), float(xs[ok].max())
    xpad = 0.04 * (xmax - xmin)
    xt = nice_ticks(xmin - xpad, xmax + xpad)
    y_lo, y_hi = float(ys[ok].min()), float(ys[ok].max())
    ylo = min(0.0, y_lo) if y_from_zero else y_lo - 0.05 * (y_hi - y_lo)
    yt = nice_ticks(ylo, y_hi + 0.08 * (y_hi - ylo))
    # margins: room for tick labels, axis labels and title
    left, right = 90, 30
    top, bottom = (50 if title else 25), 70
    x0, x1, y0, y1 = left, width - right, height - bottom, top
    if x1 - x0 < 50 or y0 - y1 < 50:
        raise ConfigError(f"plot size {width}x{height}: too small")

    def px(x, y):
        u = x0 + (x - xt[0]) / (xt[-1] - xt[0]) * (x1 - x0)
        v = y0 - (y - yt[0]) / (yt[-1] - yt[0]) * (y0 - y1)
        return int(round(u)), int(round(v))

    grid, axis = (225, 225, 225), (40, 40, 40)
    for t in xt:
        u, _ = px(t, yt[0])
        cv2.line(img, (u, y1), (u, y0), grid, 1)
        cv2.line(img, (u, y0), (u, y0 + 5), axis, 1)
        _text(img, _fmt(t, xt[1] - xt[0]), (u, y0 + 22), 0.45, axis, anchor="centre")
    for t in yt:
        _, v = px(xt[0], t)
        cv2.line(img, (x0, v), (x1, v), grid, 1)
        cv2.line(img, (x0 - 5, v), (x0, v), axis, 1)
        _text(img, _fmt(t, yt[1] - yt[0]), (x0 - 9, v + 5), 0.45, axis, anchor="right")
    cv2.rectangle(img, (x0, y1), (x1, y0), axis, 1)
    if title:
        _text(img, title, ((x0 + x1) // 2, top - 18), 0.6, axis, 1, anchor="centre")
    if xlabel:
        _text(img, xlabel, ((x0 + x1) // 2, height - 18), 0.55, axis, anchor="centre")
    if ylabel:
        (tw, th), base = cv2.getTextSize(ylabel, FONT, 0.55, 1)
        strip = np.full((th + base + 6, tw + 6, 3), 255, np.uint8)
        _text(strip, ylabel, (3, th + 3), 0.55, axis)
        strip = cv2.rotate(strip, cv2.ROTATE_90_COUNTERCLOCKWISE)
        sy = max(0, (y0 + y1) // 2 - strip.shape[0] // 2)
        sh = min(strip.shape[0], height - sy)
        img[sy : sy + sh, 12 : 12 + strip.shape[1]] = strip[:sh]

    all_pts = []
    for k, s in enumerate(series):
        colour, marker = COLOURS[k % len(COLOURS)], MARKERS[k % len(MARKERS)]
        pts = [
            px(x, y) if math.isfinite(x) and math.isfinite(y) else None
            for x, y in zip(s.x, s.y, strict=True)
        ]
        for a, b in zip(pts, pts[1:], strict=False):
            if a is not None and b is not None:
                cv2.line(img, a, b, colour, 2, cv2.LINE_AA)
        for p in pts:
            if p is not None:
                _marker(img, p, marker, colour)
        all_pts += [p for p in pts if p is not None]
    _legend(img, series, (x0, y1, x1, y0), all_pts)
    return img


def _legend(img, series, frame, points) -> None:
    if not series:
        return
    row_h, swatch = 22, 34
    widths = [cv2.getTextSize(s.label, FONT, 0.5, 1)[0][0] for s in series]
    w = swatch + 12 + max(widths) + 10
    h = row_h * len(series) + 8
    fx0, fy0, fx1, fy1 = frame
    corners = [(fx1 - 12 - w, fy0 + 12), (fx0 + 12, fy0 + 12),
               (fx1 - 12 - w, fy1 - 12 - h), (fx0 + 12, fy1 - 12 - h)]  # fmt: skip
    pts = np.array(points, dtype=np.float64).reshape(-1, 2)

    def hidden(corner):
        cx, cy = corner
        inside = (pts[:, 0] > cx - 8) & (pts[:, 0] < cx + w + 8)
        return int(np.count_nonzero(inside & (pts[:, 1] > cy - 8) & (pts[:, 1] < cy + h + 8)))

    # the corner that hides the fewest data points (top right first, like most plots)
    x, y = min(corners, key=hidden)
    cv2.rectangle(img, (x, y), (x + w, y + h), (255, 255, 255), -1)
    cv2.rectangle(img, (x, y), (x + w, y + h), (150, 150, 150), 1)
    for k, s in enumerate(series):
        colour, marker = COLOURS[k % len(COLOURS)], MARKERS[k % len(MARKERS)]
        cy = y + 4 + row_h * k + row_h // 2
        cv2.line(img, (x + 6, cy), (x + 6 + swatch, cy), colour, 2, cv2.LINE_AA)
        _marker(img, (x + 6 + swatch // 2, cy), marker, colour)
        _text(img, s.label, (x + swatch + 14, cy + 5), 0.5, (40, 40, 40))


def save_png(img: np.ndarray, path: str | Path) -> None:
    """Write a plot image; a ConfigError names the file when it cannot be written."""
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ConfigError(f"{path}: plot file must end in .png")
    ok, buf = cv2.imencode(".png", img)
    try:
        if not ok:
            raise OSError("PNG encoding failed")
        path.write_bytes(buf.tobytes())
    except OSError as exc:
        raise ConfigError(f"{path}: cannot write plot: {exc.strerror or exc}") from None
