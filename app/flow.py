"""From band lengths and intervals to light flows and their log ratio (pure numpy/OpenCV).

Flow of pattern i in line-index units is ``L_i / B_i`` (sweep over the local
line interval); in projector pixels it is that times the local pitch
``P_i(u)``.  Two projectors: ``log ratio = log(L_1/B_1) - log(L_2/B_2)``.  One
projector with the exp2 pair: both patterns share the sweep, so the ratio of
the flows is the ratio of the intervals, ``B_2 / B_1``, which is measured far
more precisely than a sweep; the sweeps still decide which pixels move.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .patterns import local_pitch
from .profile_model import fit_blur, tables
from .rig import Rig


@dataclass(frozen=True)
class FlowParams:
    """Options of the flow stage.

    Attributes
    ----------
    smoothing_px : float
        Gaussian sigma, in camera pixels, of the masked smoothing of the log
        flow ratio (the paper uses 2 to 60); 0 disables it.
    static_factor : float
        A band counts as moving only if its length exceeds the line width in
        camera pixels times this factor plus ``static_margin_px``.
    static_margin_px : float
    outlier_sigmas : float
        Pixels whose log ratio is further than this many robust deviations
        from the smoothed field are dropped before the final smoothing.
    """

    smoothing_px: float = 10.0
    static_factor: float = 1.3
    static_margin_px: float = 1.0
    outlier_sigmas: float = 3.0
    blur_refit_frames: int = 30


class FlowModel:
    """Pattern geometry needed to turn band measurements into flows for one rig."""

    def __init__(self, rig: Rig):
        self.rig = rig
        self.single = rig.single_projector
        self.pairs = rig.patterns
        #: per pattern, fitted blur model (a, b): sigma^2 = a + b * magnification^2
        self.blur: list[tuple[float, float] | None] = [None, None]
        self.frames = 0
        if self.single:
            proj = rig.projectors[0]
            # u from the interval ratio B2/B1 = P2(u)/P1(u), monotonic in u for the exp2 pair
            u = np.linspace(-0.5, proj.width - 0.5, 4096)
            ratio = local_pitch(self.pairs[1][1], proj.width, u) / local_pitch(
                self.pairs[0][1], proj.width, u
            )
            order = np.argsort(ratio)
            self._u_of_log_ratio = (np.log(ratio[order]), u[order])

    def projector_column(self, log_ratio: np.ndarray) -> np.ndarray:
        """Single projector: the projector column u implied by the interval ratio."""
        xp, fp = self._u_of_log_ratio
        return np.interp(log_ratio, xp, fp, left=np.nan, right=np.nan)

    def combine(
        self, maps: list[np.ndarray], params: FlowParams
    ) -> tuple[np.ndarray, list[np.ndarray], list[float]]:
        """Per-pixel raw log ratio and the two flows in projector pixels (NaN = invalid).

        Parameters
        ----------
        maps : list of numpy.ndarray
            Per pattern, ``(3, h, w)`` grid maps of the measured band width at half
            height ``m``, the line interval ``B`` and the 50->20 % ramp ``r`` (camera px).
        params : FlowParams

        Returns
        -------
        log_ratio : numpy.ndarray
        flows : list of numpy.ndarray
            Flows in projector pixels.
        blur : list of float
            Per pattern, the blur sigma (camera px) at the median magnification.
        """
        tab = tables()
        with np.errstate(invalid="ignore", divide="ignore"):
            intervals = [mp[1] for mp in maps]
            if self.single:
                u = self.projector_column(np.log(intervals[1] / intervals[0]))
                pitches = [local_pitch(pat, proj.width, u) for proj, pat in self.pairs]
            else:
                pitches = [np.float64(pat.pitch_px) for _, pat in self.pairs]
            flows, lengths, blur = [], [], []
            refit = self.frames % params.blur_refit_frames == 0
            for i, ((_, pat), (m, B, r), P) in enumerate(
                zip(self.pairs, maps, pitches, strict=True)
            ):
                scale = B / P  # camera px per projector px, locally
                line = pat.width_px * scale
                if refit or self.blur[i] is None:
                    fitted = fit_blur(m, r, line, scale)
                    if fitted is not None:
                        self.blur[i] = fitted
                a, b = self.blur[i] or (1.0, 0.0)
                sigma = np.sqrt(a + b * scale * scale)
                blur.append(float(np.nanmedian(sigma)) if np.isfinite(sigma).any() else np.nan)
                L = tab.true_length(m, line, sigma)
                L[~(L > params.static_factor * line + params.static_margin_px)] = np.nan
                lengths.append(L)
                flows.append((L / B * P).astype(np.float32))
            if self.single:
                # same projector: the flow ratio is the interval ratio (sweeps only gate)
                log_ratio = np.log(intervals[1] / intervals[0])
            else:
                log_ratio = np.log(lengths[0] / intervals[0]) - np.log(lengths[1] / intervals[1])
            moving = np.isfinite(lengths[0]) & np.isfinite(lengths[1])
            log_ratio = np.where(moving, log_ratio, np.nan).astype(np.float32)
        for f in flows:
            f[~moving] = np.nan
        self.frames += 1
        return log_ratio, flows, blur


def masked_smooth(values: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing that ignores NaN pixels and keeps them NaN."""
    mask = np.isfinite(values)
    if sigma <= 0:
        return values
    m = mask.astype(np.float32)
    v = np.where(mask, values, 0).astype(np.float32)
    num = cv2.GaussianBlur(v, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
    den = cv2.GaussianBlur(m, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = num / den
    out[~mask] = np.nan
    return out


def smooth_log_ratio(log_ratio: np.ndarray, sigma: float, outlier_sigmas: float) -> np.ndarray:
    """Robust masked smoothing: drop outliers against a first smoothing, then smooth again."""
    if sigma <= 0:
        return log_ratio
    first = masked_smooth(log_ratio, sigma)
    resid = np.abs(log_ratio - first)
    finite = resid[np.isfinite(resid)]
    if finite.size < 16:
        return first
    mad = float(np.median(finite)) * 1.4826 + 1e-6
    cleaned = np.where(resid <= outlier_sigmas * mad, log_ratio, np.nan)
    return masked_smooth(cleaned, sigma)
