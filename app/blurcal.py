"""Measure the blur of each pattern's lines on static frames (``lightflow rig blur``).

Short sweeps (a fan at 1 ms, a ball at 5 ms) move their lines less than the
lines' own width: the sweep then shows only in the ramps of the band, and
reading it needs the blur of the optics.  Without a measurement the pipeline
fits the blur on the moving bands of the first frames, which is noisy and
biased on short bands.  Lines that stand still measure it directly: their
width is known from the rig, so their ramps give the blur.  Seen at several
depths (magnifications), the camera's part (fixed in camera pixels) and the
projector's defocus (fixed in projector pixels) separate
(:func:`lightflow.app.core.profile_model.static_blur`).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from lightflow.app.core.errors import CalibrationError
from lightflow.app.core.pipeline import DepthPipeline, PipelineConfig
from lightflow.app.core.profile_model import static_blur
from lightflow.app.core.rig import Rig

#: magnifications must span this ratio for the projector's part to be told from the camera's
MIN_MAGNIFICATION_SPAN = 1.15


@dataclass(frozen=True)
class PatternBlur:
    """The blur measured for one pattern.

    Attributes
    ----------
    camera_px2, projector_px2 : float
        ``sigma^2 = camera_px2 (1 + slant^2) + projector_px2 m^2`` (camera px^2).
    lines : int
        Static line measurements (grid cells) used.
    magnification : tuple of float
        5th and 95th percentile of the magnification m (camera px per projector
        px) over those lines; a narrow span cannot separate the two parts, and
        the whole blur is then given to the camera (``projector_px2 = 0``).
    """

    camera_px2: float
    projector_px2: float
    lines: int
    magnification: tuple

    def sigma_px(self, m: float) -> float:
        """Blur sigma (camera px) of upright lines at magnification ``m``."""
        return float(np.sqrt(self.camera_px2 + self.projector_px2 * m * m))


def measure_blur(rig: Rig, frames: Iterable, stride: int = 4) -> list[PatternBlur]:
    """Measure each pattern's blur on frames of static surfaces.

    Parameters
    ----------
    rig : Rig
    frames : iterable of Frame
        Frames whose lines stand still (any exposure), best of surfaces at
        several depths across the working range.
    stride : int
        Analysis grid stride.

    Returns
    -------
    list of PatternBlur
        One per pattern, in the rig's order.

    Raises
    ------
    CalibrationError
        When a pattern shows too few static lines.
    """
    pipeline = DepthPipeline(rig, PipelineConfig(stride=stride))
    samples: list[list[np.ndarray]] = [[], []]
    n = 0
    for frame in frames:
        lines = pipeline.flow_model.line_samples(pipeline.band_grids(frame))
        for p in range(2):
            samples[p].append(lines[p])
        n += 1
    if n == 0:
        raise CalibrationError("rig blur: no frames to measure")
    out = []
    for p, (_, pat) in enumerate(rig.patterns):
        m, r, line, scale, slant = np.concatenate(samples[p], axis=1)
        fit = static_blur(m, r, line, scale, slant)
        if fit is None:
            raise CalibrationError(
                f"rig blur: pattern {p + 1} ({pat.channel}): too few static lines in {n} "
                f"frame(s); expected still surfaces lit by the pattern, in focus range"
            )
        a, b, used = fit
        seen = scale[np.isfinite(scale) & np.isfinite(m)]
        lo, hi = (float(v) for v in np.percentile(seen, [5, 95]))
        out.append(PatternBlur(a, b, used, (lo, hi)))
    return out
