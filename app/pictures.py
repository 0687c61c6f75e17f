"""One picture per evaluated recording: where the depth is, how far off, and why not.

``lightflow eval --pictures DIR`` draws, for the last frame of each recording,
three panels side by side:

1. the camera image (brightened: rendered frames are dark);
2. the signed depth error (estimate minus truth, mm) on a diverging scale, the
   moving object without a depth in grey, and depth off the object in magenta;
3. why the moving object got no depth, one colour per cause (the colours of the
   Rerun view's causes panel), with each cause's share of the object.

The figure is drawn with matplotlib on its own Agg canvas (no pyplot, no
display), like :mod:`lightflow.app.plot`.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.cm import ScalarMappable
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from lightflow.app.core.causes import CAUSE_COLOURS, CAUSE_NAMES, DEPTH
from lightflow.app.plot import save_png

#: the error scale's limits, mm (the same for every case, so pictures compare)
ERROR_RANGE_MM = 40.0
#: colours of the error panel beyond the diverging scale (RGB, 0-1)
NO_DEPTH_RGB = (0.55, 0.55, 0.55)
OFF_OBJECT_RGB = (1.0, 0.0, 1.0)
BACKGROUND_RGB = (0.0, 0.0, 0.0)
DPI = 100


def _brightened(image: np.ndarray) -> np.ndarray:
    """RGB float in 0-1, scaled so that the 99.5th percentile is white."""
    rgb = image.astype(np.float32)
    if rgb.ndim == 2:
        rgb = np.repeat(rgb[..., None], 3, axis=-1)
    top = float(np.percentile(rgb, 99.5)) or 1.0
    return np.clip(rgb / top, 0.0, 1.0)


def error_rgb(depth: np.ndarray, truth_depth: np.ndarray, target: np.ndarray,
              moving: np.ndarray) -> np.ndarray:  # fmt: skip
    """RGB float ``(H, W, 3)`` of the signed depth error, as the middle panel draws it.

    Parameters
    ----------
    depth, truth_depth : numpy.ndarray
        ``(H, W)`` estimated and true z (m), NaN without.
    target : numpy.ndarray
        ``(H, W)`` bool: the pixels the coverage counts (moving, lit by every projector).
    moving : numpy.ndarray
        ``(H, W)`` bool: every pixel of a moving object (depth there is not "off").
    """
    import matplotlib

    err = (depth - truth_depth) * 1e3
    have = np.isfinite(depth)
    t = np.clip(0.5 + 0.5 * np.nan_to_num(err) / ERROR_RANGE_MM, 0.0, 1.0)
    rgb = matplotlib.colormaps["RdBu_r"](t)[..., :3]
    out = np.empty(depth.shape + (3,), np.float32)
    out[:] = BACKGROUND_RGB
    out[target & ~have] = NO_DEPTH_RGB
    on = have & moving & np.isfinite(err)
    out[on] = rgb[on]
    out[have & ~moving] = OFF_OBJECT_RGB
    return out


def case_picture(image: np.ndarray, depth: np.ndarray, truth, target: np.ndarray,
                 causes_grid: np.ndarray | None, stride: int, title: str,
                 path: str | Path) -> None:  # fmt: skip
    """Draw the three panels of one frame and write them to ``path`` (PNG).

    Parameters
    ----------
    image : numpy.ndarray
        The camera frame, ``(H, W)`` or ``(H, W, 3)`` RGB.
    depth : numpy.ndarray
        ``(H, W)`` estimated z (m), NaN without.
    truth : GroundTruth
        The frame's ground truth (``depth``, ``object_id``).
    target : numpy.ndarray
        ``(H, W)`` bool: the pixels the coverage counts.
    causes_grid : numpy.ndarray, optional
        The analysis grid's cause codes (:mod:`lightflow.app.core.causes`).
    stride : int
        Camera pixels per grid cell.
    title : str
        Above the panels (the case and its figures).
    path : str or Path
        The PNG to write; a ConfigError names it when it cannot be written.
    """
    h, w = depth.shape
    moving = truth.object_id >= 2
    panels = [_brightened(image), error_rgb(depth, truth.depth, target, moving)]
    legend = []
    if causes_grid is not None:
        grid_target = cv2.resize(target.view(np.uint8), causes_grid.shape[::-1],
                                 interpolation=cv2.INTER_NEAREST).view(bool)  # fmt: skip
        colours = np.array(CAUSE_COLOURS, np.float32) / 255.0
        causes = np.full(causes_grid.shape + (3,), 0.0, np.float32)
        causes[grid_target] = colours[causes_grid[grid_target]]
        causes = cv2.resize(causes, (causes_grid.shape[1] * stride, causes_grid.shape[0] * stride),
                            interpolation=cv2.INTER_NEAREST)[:h, :w]  # fmt: skip
        panels.append(causes)
        codes, counts = np.unique(causes_grid[grid_target], return_counts=True)
        total = max(1, int(counts.sum()))
        for code, n in sorted(zip(codes.tolist(), counts.tolist(), strict=True),
                              key=lambda cn: -cn[1]):  # fmt: skip
            share = 100.0 * n / total
            if code == DEPTH or share >= 0.5:
                label = f"{CAUSE_NAMES[code]} {share:.0f} %"
                legend.append(Patch(color=colours[code], label=label))
    names = ["camera image", f"depth error (mm), ±{ERROR_RANGE_MM:.0f}: grey none, magenta off "
             "the object", "why the moving object has no depth"]  # fmt: skip
    panel_in = 4.2  # inches per panel; the legend and the error scale go below
    fig = Figure(figsize=(panel_in * len(panels), panel_in * h / w + 1.2), dpi=DPI,
                 facecolor="white")  # fmt: skip
    canvas = FigureCanvasAgg(fig)
    axes = fig.subplots(1, len(panels))
    fig.subplots_adjust(left=0.01, right=0.99, top=1.0 - 0.45 / fig.get_figheight(),
                        bottom=0.8 / fig.get_figheight(), wspace=0.04)  # fmt: skip
    for ax, panel, name in zip(axes, panels, names, strict=False):
        ax.imshow(panel, interpolation="nearest")
        ax.set_title(name, fontsize=8)
        ax.set_axis_off()
    scale = ScalarMappable(Normalize(-ERROR_RANGE_MM, ERROR_RANGE_MM), cmap="RdBu_r")
    bar = fig.colorbar(scale, cax=axes[1].inset_axes((0.1, -0.09, 0.8, 0.045)),
                       orientation="horizontal")  # fmt: skip
    bar.ax.tick_params(labelsize=7)
    if legend:
        axes[-1].legend(handles=legend, loc="upper center", bbox_to_anchor=(0.5, 0.0),
                        ncol=3, fontsize=7, frameon=False)  # fmt: skip
    fig.suptitle(title, fontsize=9)
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())
    save_png(np.ascontiguousarray(rgba[..., 2::-1]), path)
