"""Line plots with matplotlib (Agg, no display): axes, ticks, labels, legend.

Used by ``lightflow eval`` to draw depth error against exposure.  Images are
BGR uint8 arrays, as :func:`cv2.imwrite` expects.  Figures are drawn on their
own Agg canvas (no pyplot, no global state), so plotting needs no display and
is safe from any thread.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from lightflow.app.core.errors import ConfigError

#: a colour-blind-safe cycle (Okabe-Ito), BGR like the images
COLOURS = (
    (178, 114, 0), (0, 94, 213), (115, 158, 0), (167, 121, 204), (233, 180, 86),
    (66, 228, 240), (0, 0, 0),
)  # fmt: skip
#: matplotlib marker per series: circle, square, triangle, diamond
MARKERS = ("o", "s", "^", "D")
DPI = 100


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


def _rgb(bgr: tuple[int, int, int]) -> tuple[float, float, float]:
    return bgr[2] / 255.0, bgr[1] / 255.0, bgr[0] / 255.0


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
    if width < 200 or height < 150:
        raise ConfigError(f"plot size {width}x{height}: too small")
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

    fig = Figure(figsize=(width / DPI, height / DPI), dpi=DPI, facecolor="white")
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    axis = _rgb((40, 40, 40))
    ax.set_xlim(xt[0], xt[-1])
    ax.set_ylim(yt[0], yt[-1])
    ax.set_xticks(xt, [_fmt(t, xt[1] - xt[0]) for t in xt])
    ax.set_yticks(yt, [_fmt(t, yt[1] - yt[0]) for t in yt])
    ax.grid(True, color=_rgb((225, 225, 225)), linewidth=1)
    ax.set_axisbelow(True)
    ax.tick_params(colors=axis, labelsize=9)
    for spine in ax.spines.values():
        spine.set_color(axis)
    if title:
        ax.set_title(title, color=axis, fontsize=11)
    if xlabel:
        ax.set_xlabel(xlabel, color=axis, fontsize=10)
    if ylabel:
        ax.set_ylabel(ylabel, color=axis, fontsize=10)
    for k, s in enumerate(series):
        # NaN values break the line, as matplotlib draws them
        ax.plot(
            np.asarray(s.x, np.float64), np.asarray(s.y, np.float64),
            color=_rgb(COLOURS[k % len(COLOURS)]), marker=MARKERS[k % len(MARKERS)],
            markersize=7, linewidth=2, label=s.label,
        )  # fmt: skip
    if series:
        # the place that hides the fewest data points
        ax.legend(loc="best", fontsize=9, edgecolor=_rgb((150, 150, 150)), framealpha=1.0)
    fig.tight_layout()
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())
    if rgba.shape[:2] != (height, width):
        rgba = cv2.resize(rgba, (width, height), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(rgba[..., 2::-1])


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
