"""Projector response (gamma) from camera images of a grey ramp.

The projector shows uniform grey levels one after another on a white surface;
the camera (linear) sees ``I(L) = a + b * r(L / 255)``.  Normalising by the
black and white frames removes ambient light, projector black level and
albedo: ``r(L) = (I(L) - I(0)) / (I(255) - I(0))``, fitted by ``v ** gamma``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from lightflow.app.errors import CalibrationError


@dataclass(frozen=True)
class Response:
    """A measured projector response.

    Attributes
    ----------
    gamma : float
        Best fit of ``r(v) = v ** gamma`` with ``v = level / 255``.
    levels : numpy.ndarray
        The grey levels shown.
    response : numpy.ndarray
        Normalised camera response at each level (0 at black, 1 at white).
    rms : float
        RMS of the fit residual in normalised units.
    inverse : numpy.ndarray
        ``(256,)`` uint8 table: the grey level to show for a linear output
        ``i / 255`` (interpolated from the measured response).
    """

    gamma: float
    levels: np.ndarray
    response: np.ndarray
    rms: float
    inverse: np.ndarray

    def summary_lines(self) -> list[str]:
        pairs = "  ".join(f"{int(lv)}:{r:.3f}" for lv, r in zip(self.levels, self.response,
                                                               strict=True))
        return [f"projector response: gamma {self.gamma:.3f} (fit RMS {self.rms:.4f})",
                f"  level:response  {pairs}"]


def measure_response(images: Sequence[np.ndarray], levels: Sequence[int],
                     min_contrast: float = 20.0, saturation: float = 250.0) -> Response:
    """Fit the projector's gamma from camera images of uniform grey levels.

    Parameters
    ----------
    images : sequence of numpy.ndarray
        One grey (or colour, averaged) camera image per level.
    levels : sequence of int
        Grey levels 0..255 shown; must include 0 and 255.
    min_contrast : float
        Pixels whose white-minus-black difference is below this are ignored.
    saturation : float
        Pixels at or above this level in the white image are ignored (clipped).

    Raises
    ------
    CalibrationError
        Levels 0 or 255 missing, or no pixel lit with enough contrast.
    """
    levels = np.asarray(levels, float)
    if len(images) != len(levels):
        raise CalibrationError(f"grey ramp: {len(images)} images for {len(levels)} levels")
    if 0 not in levels or 255 not in levels:
        raise CalibrationError("grey ramp: levels must include 0 (black) and 255 (white)")
    stack = np.stack([np.asarray(im, np.float32).reshape(im.shape[0], im.shape[1], -1).mean(-1)
                      for im in images])
    black = stack[int(np.flatnonzero(levels == 0)[0])]
    white = stack[int(np.flatnonzero(levels == 255)[0])]
    mask = ((white - black) >= min_contrast) & (white < saturation)
    if mask.sum() < 100:
        raise CalibrationError(f"grey ramp: only {int(mask.sum())} pixels brighten by "
                               f"{min_contrast} grey levels from black to white without "
                               f"saturating")
    # ratio of sums over the lit pixels: robust to per-pixel noise
    response = (stack[:, mask] - black[mask]).sum(1) / (white[mask] - black[mask]).sum()
    v = levels / 255.0
    use = (v > 0.02) & (v < 1.0) & (response > 1e-3)
    if use.sum() < 1:
        raise CalibrationError("grey ramp: need at least one level between 5 and 254")
    lv, lr = np.log(v[use]), np.log(response[use])
    gamma = float((lv * lr).sum() / (lv * lv).sum())
    rms = float(np.sqrt(np.mean((response - v**gamma) ** 2)))
    order = np.argsort(levels)
    r_sorted = np.maximum.accumulate(np.clip(response[order], 0, 1))
    inverse = np.interp(np.arange(256) / 255.0, r_sorted, levels[order])
    inverse = np.clip(np.rint(inverse), 0, 255).astype(np.uint8)
    return Response(gamma, levels, response, rms, inverse)
