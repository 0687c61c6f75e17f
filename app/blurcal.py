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

The same lines give the camera's response curve first (:func:`measure_response`):
a static line's ramp gives its blur, the blur and its known width give its
width at half height, and a camera that is not linear reads every line wider.
And they give the colour crosstalk between the two patterns' channels
(:func:`measure_crosstalk`): still lines leave the clean gaps its estimate needs.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from lightflow.app.core.errors import CalibrationError
from lightflow.app.core.pipeline import DepthPipeline, PipelineConfig
from lightflow.app.core.profile_model import static_blur
from lightflow.app.core.response import MIN_STILL_LINES, find_gamma
from lightflow.app.core.rig import Rig

#: magnifications must span this ratio for the projector's part to be told from the camera's
MIN_MAGNIFICATION_SPAN = 1.15


@dataclass(frozen=True)
class CameraResponse:
    """The camera's response curve measured on static lines.

    Attributes
    ----------
    gamma : float
        ``DN = full * (light / full) ** (1 / gamma)``; exactly 1 when the
        measurement was close to it.
    measured : float
        The measurement itself, before that snap (``LINEAR_SNAP`` of
        :mod:`lightflow.app.core.response`).
    lines : int
        Static line measurements (grid cells) at the answer.
    excess_linear_px : float
        How much wider the lines read at half height when taken as linear (camera px).
    """

    gamma: float
    measured: float
    lines: int
    excess_linear_px: float


def measure_response(rig: Rig, frames: Iterable, stride: int = 4) -> CameraResponse:
    """The camera's gamma from frames of static surfaces (:func:`lightflow.app.core.response.
    find_gamma` over their static lines).

    Parameters
    ----------
    rig : Rig
    frames : iterable of Frame
        As for :func:`measure_blur`.
    stride : int

    Returns
    -------
    CameraResponse

    Raises
    ------
    CalibrationError
        Too few static lines, or no candidate makes them as wide as the model.
    """
    frames = list(frames)
    if not frames:
        raise CalibrationError("rig blur: no frames to measure")
    pipeline = DepthPipeline(rig, PipelineConfig(stride=stride))

    def excess(log_gamma: float):
        return pipeline.still_line_excess(float(np.exp(log_gamma)), frames)

    at_linear = excess(0.0)
    found = find_gamma(excess, MIN_STILL_LINES)
    if found is None:
        raise CalibrationError(
            f"rig blur: the camera's response could not be measured on {len(frames)} frame(s): "
            f"expected still surfaces lit by both patterns, in focus range"
        )
    gamma, measured, lines = found
    return CameraResponse(gamma, measured, lines,
                          at_linear[0] if at_linear is not None else float("nan"))  # fmt: skip


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


def measure_crosstalk(rig: Rig, frames: Iterable, stride: int = 4) -> list[float | None]:
    """Each pattern's colour crosstalk on frames of static surfaces.

    Across each still line of one pattern, the other pattern's camera channel rises by
    the crosstalk times the line's height, where no line of its own reaches
    (:func:`lightflow.app.core.bands.estimate_leak`).  Still lines leave wide, clean
    gaps, which moving bands often do not.

    Parameters
    ----------
    rig : Rig
        With the camera's response already measured (the estimate is in linear values).
    frames : iterable of Frame
        Frames whose lines stand still (see :func:`measure_blur`).
    stride : int

    Returns
    -------
    list of float or None
        Per pattern (file order), the median of the frames' estimates; None where no
        frame gave one.
    """
    pipeline = DepthPipeline(rig, PipelineConfig(stride=stride))
    estimates = np.array([pipeline.estimate_crosstalk(frame) for frame in frames]).reshape(-1, 2)
    out: list[float | None] = []
    for p in range(2):
        seen = estimates[np.isfinite(estimates[:, p]), p]
        out.append(float(np.median(seen)) if seen.size else None)
    return out


def calibrate_optics(rig: Rig, frames: Iterable, stride: int = 4):
    """The camera's response, then each pattern's blur and crosstalk in linear values: what
    ``rig blur`` does.

    Parameters
    ----------
    rig : Rig
    frames : iterable of Frame
        Frames of static surfaces (see :func:`measure_blur`).
    stride : int

    Returns
    -------
    (Rig, CameraResponse or None, list of PatternBlur)
        The rig with the measured ``camera.gamma``, blur and crosstalk; the response
        is None (and the rig's gamma kept) when it could not be measured, and the
        rig's crosstalk is kept unless every pattern's was measured.
    """
    frames = list(frames)
    try:
        response = measure_response(rig, frames, stride)
    except CalibrationError:
        response = None
    if response is not None:
        rig = rig.with_camera_gamma(response.gamma)
    blurs = measure_blur(rig, frames, stride)
    crosstalk = measure_crosstalk(rig, frames, stride)
    if all(c is not None for c in crosstalk):
        rig = rig.with_crosstalk(crosstalk)
    return rig.with_blur((pb.camera_px2, pb.projector_px2) for pb in blurs), response, blurs
