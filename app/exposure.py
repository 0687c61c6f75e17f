"""Blur-aware auto exposure: choose the exposure from the measured band lengths.

The paper shows depth accuracy improving as the bands get longer, until
neighbouring bands overlap and can no longer be measured.  The band length
(the sweep of a line during the exposure) grows in proportion to the
exposure, so the exposure is scaled multiplicatively until the longest bands
are long but clearly shorter than the line interval.

What is measured (from :class:`~lightflow.app.core.results.BandSet` only): in each
image row the bands of one pattern are sorted by position; for each pair of
neighbours the *fraction* is their mean length over the distance between
their centres (the local line interval in camera pixels).  The statistic is
the 90th percentile of the fractions of a pattern, and the larger of the two
patterns decides (whichever overlaps first).  A high percentile follows the
fast parts of the scene, which are the ones that overlap first, and merged
(overlapping) bands show up as large fractions, which shortens the exposure.

Measured on the synthetic board with the two-projector rig (scale 0.25): the
statistic is about 0.2 for static lines (the line width plus optical blur),
0.5 where the coverage was best, and 0.7-0.85 once the bands of the faster
pattern had merged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lightflow.app.core.errors import ConfigError
from lightflow.app.core.results import BandSet, FrameResult

PERCENTILE = 90.0


@dataclass(frozen=True)
class BandMeasure:
    """Band length as a fraction of the line interval for one pattern of one frame."""

    channel: str
    fraction: float
    length_px: float
    interval_px: float
    pairs: int


@dataclass(frozen=True)
class ExposureDecision:
    """What auto exposure chose and why.

    Attributes
    ----------
    exposure_s : float
        The exposure to use from now on (equal to ``previous_s`` when unchanged).
    previous_s : float
    fraction : float
        The measured band length over line interval (NaN when not measurable).
    length_px : float
        The measured band length in camera pixels (NaN when not measurable).
    changed : bool
    reason : str
        Plain words, e.g. ``bands 6.1 px = 0.15 of the interval: too short, exposure 10 -> 22 ms``.
    """

    exposure_s: float
    previous_s: float
    fraction: float
    length_px: float
    changed: bool
    reason: str


def measure_bands(bands: BandSet, percentile: float = PERCENTILE) -> BandMeasure | None:
    """Band length over line interval of one pattern, None with fewer than 20 neighbour pairs."""
    if len(bands.rows) < 2:
        return None
    rows = np.asarray(bands.rows, np.float64)
    starts = np.asarray(bands.starts, np.float64)
    ends = np.asarray(bands.ends, np.float64)
    order = np.lexsort((starts, rows))
    rows, starts, ends = rows[order], starts[order], ends[order]
    centres = 0.5 * (starts + ends)
    lengths = ends - starts
    same_row = rows[1:] == rows[:-1]
    interval = np.diff(centres)[same_row]
    length = 0.5 * (lengths[1:] + lengths[:-1])[same_row]
    ok = (interval > 0) & np.isfinite(interval) & np.isfinite(length)
    if np.count_nonzero(ok) < 20:
        return None
    frac = length[ok] / interval[ok]
    f = float(np.percentile(frac, percentile))
    # the length and interval reported are those of the pairs around that percentile
    near = np.abs(frac - f) <= 0.02 + 0.05 * f
    return BandMeasure(
        bands.channel,
        f,
        float(np.median(length[ok][near])),
        float(np.median(interval[ok][near])),
        int(np.count_nonzero(ok)),
    )


class BlurAwareExposure:
    """Adjust the exposure so that the longest bands sit in the best range.

    Parameters
    ----------
    target_fraction : float
        Band length / line interval aimed at when the exposure is changed.
    band : (float, float)
        Hysteresis: the exposure is left alone while the measured fraction is
        inside this range (so it does not hunt frame to frame).
    min_s, max_s : float
        Exposure limits (seconds); ``max_s`` is usually the frame period.
    max_step : float
        Largest factor of one change (noisy measurements cannot jump far).
    """

    def __init__(
        self,
        target_fraction: float = 0.5,
        band: tuple[float, float] = (0.4, 0.62),
        min_s: float = 50e-6,
        max_s: float = 0.1,
        max_step: float = 4.0,
    ):
        lo, hi = band
        if not 0 < lo < target_fraction < hi < 1:
            raise ConfigError(
                f"auto exposure: need 0 < band low < target < band high < 1, got "
                f"band {band}, target {target_fraction}"
            )
        if not 0 < min_s < max_s:
            raise ConfigError(f"auto exposure: need 0 < min_s < max_s, got {min_s}, {max_s}")
        self.target = target_fraction
        self.band = (lo, hi)
        self.min_s = min_s
        self.max_s = max_s
        self.max_step = max_step

    def measure(self, result: FrameResult) -> BandMeasure | None:
        """The pattern whose bands are longest relative to their interval."""
        found = [m for m in (measure_bands(b) for b in result.bands) if m is not None]
        return max(found, key=lambda m: m.fraction) if found else None

    def update(self, result: FrameResult, exposure_s: float | None = None) -> ExposureDecision:
        """Decide the next exposure from one processed frame.

        Parameters
        ----------
        result : FrameResult
        exposure_s : float, optional
            The exposure now in use (default: the frame's).
        """
        old = float(exposure_s if exposure_s is not None else result.frame.exposure_s)
        m = self.measure(result)
        if m is None:
            return ExposureDecision(
                old, old, math.nan, math.nan, False,
                f"too few bands to measure: keeping exposure {_ms(old)} ms",
            )  # fmt: skip
        lo, hi = self.band
        what = (
            f"bands {m.length_px:.1f} px = {m.fraction:.2f} of the interval "
            f"({m.interval_px:.1f} px, {m.channel})"
        )
        if lo <= m.fraction <= hi:
            return ExposureDecision(
                old, old, m.fraction, m.length_px, False,
                f"{what}: in the best range {lo:.2f}-{hi:.2f}, exposure stays {_ms(old)} ms",
            )  # fmt: skip
        # the sweep grows in proportion to the exposure
        factor = min(self.max_step, max(1.0 / self.max_step, self.target / m.fraction))
        new = min(self.max_s, max(self.min_s, old * factor))
        verdict = "too short" if m.fraction < lo else "too long (bands close to overlapping)"
        if math.isclose(new, old, rel_tol=1e-3):
            limit = "longest" if m.fraction < lo else "shortest"
            return ExposureDecision(
                old, old, m.fraction, m.length_px, False,
                f"{what}: {verdict}, but {_ms(old)} ms is already the {limit} allowed",
            )  # fmt: skip
        return ExposureDecision(
            new, old, m.fraction, m.length_px, True,
            f"{what}: {verdict}, exposure {_ms(old)} -> {_ms(new)} ms",
        )  # fmt: skip


def _ms(seconds: float) -> str:
    return f"{seconds * 1e3:.3g}"


def settle_exposure(
    camera,
    pipeline,
    controller: BlurAwareExposure,
    max_frames: int = 40,
    log=None,
) -> tuple[float, list[ExposureDecision]]:
    """Run the camera until auto exposure settles, before the real run starts.

    Frames taken with an older exposure than the one just set are skipped
    (cameras apply a new exposure a frame or two late).  Settled means two
    measured frames in a row left the exposure unchanged.

    Parameters
    ----------
    camera : Camera
        Opened; its :meth:`frames` iterator is ended afterwards.
    pipeline : DepthPipeline
    controller : BlurAwareExposure
    max_frames : int
        Give up (keeping the last exposure) after this many frames.
    log : callable, optional
        ``log(text)`` for each decision.

    Returns
    -------
    exposure_s : float
        The exposure in use at the end (read back from the camera).
    decisions : list of ExposureDecision
    """
    current = camera.exposure_s
    decisions: list[ExposureDecision] = []
    steady = 0
    frames = camera.frames()
    try:
        for n, frame in enumerate(frames):
            if n >= max_frames:
                if log:
                    log(f"auto exposure: not settled after {max_frames} frames, "
                        f"keeping {_ms(current)} ms")
                break
            if not math.isclose(frame.exposure_s, current, rel_tol=1e-3):
                continue  # taken before the last change reached the sensor
            decision = controller.update(pipeline.process(frame), current)
            decisions.append(decision)
            if log:
                log(f"auto exposure: {decision.reason}")
            if decision.changed:
                current = camera.set_exposure(decision.exposure_s)
                steady = 0
            elif math.isfinite(decision.fraction):
                steady += 1
                if steady >= 2:
                    break
    finally:
        close = getattr(frames, "close", None)
        if close is not None:
            close()  # ends the generator (a live camera stops streaming)
    return current, decisions
