"""Projector response (gamma) from camera images of a grey ramp.

The projector shows uniform grey levels one after another on a white surface;
the camera (linear) sees ``I(L) = a + b * r(L / 255)``.  Normalising by the
black and white frames removes ambient light, projector black level and
albedo: ``r(L) = (I(L) - I(0)) / (I(255) - I(0))``, fitted by ``v ** gamma``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lightflow.app.core.errors import CalibrationError


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


# ----------------------------------------------------------------------------- CAL/gamma/

#: the grey ramp folder beside a session: ``CAL/gamma/<projector>/NNN.png`` + ``ramp.json``
RAMP_DIR = "gamma"
RAMP_FILE = "ramp.json"
RAMP_FORMAT = "lightflow-gamma-ramp/1"
#: grey levels shown by default (black and white first, then the ramp)
DEFAULT_LEVELS = (0, 255, 16, 32, 64, 96, 128, 160, 192, 224)
#: a fitted gamma further than this from 1 gets a plain-words note
NONLINEAR_TOLERANCE = 0.15


def ramp_frame_path(projector: str, index: int) -> str:
    """Path of a ramp frame relative to the session folder: ``gamma/left/000.png``."""
    return f"{RAMP_DIR}/{projector}/{index:03d}.png"


def write_ramp_index(root: str | Path, levels: Sequence[int], projectors: Sequence[str]) -> Path:
    """Write ``CAL/gamma/ramp.json`` listing the grey levels and the projectors' frames."""
    import json

    levels = [int(v) for v in levels]
    doc = {
        "format": RAMP_FORMAT,
        "levels": levels,
        "projectors": {name: [ramp_frame_path(name, i) for i in range(len(levels))]
                       for name in projectors},
    }
    file = Path(root) / RAMP_DIR / RAMP_FILE
    file.parent.mkdir(parents=True, exist_ok=True)
    file.write_text(json.dumps(doc, indent=2) + "\n")
    return file


def measure_ramps(root: str | Path) -> dict[str, Response | str] | None:
    """Measure every projector's response from ``CAL/gamma/``, if the folder is there.

    Returns
    -------
    dict or None
        ``None`` without ``CAL/gamma/ramp.json``; else projector name -> its
        :class:`Response`, or a plain-words reason why it could not be measured.

    Raises
    ------
    ConfigError
        A malformed ``ramp.json`` (names the field).
    """
    from lightflow.app.core.errors import ConfigError, FrameError
    from lightflow.app.core.rig import read_json

    from .session import load_grey

    root = Path(root)
    file = root / RAMP_DIR / RAMP_FILE
    if not file.is_file():
        return None
    doc = read_json(file)
    if not isinstance(doc, dict) or doc.get("format") != RAMP_FORMAT:
        raise ConfigError(f"{file}: format: expected {RAMP_FORMAT!r}")
    levels = doc.get("levels")
    if (not isinstance(levels, list) or not levels
            or not all(isinstance(v, int) and 0 <= v <= 255 for v in levels)):
        raise ConfigError(f"{file}: levels: expected a list of grey levels 0..255")
    projs = doc.get("projectors")
    if not isinstance(projs, dict):
        raise ConfigError(f"{file}: projectors: expected an object name -> frame files")
    out: dict[str, Response | str] = {}
    for name, files in projs.items():
        if not isinstance(files, list) or len(files) != len(levels):
            raise ConfigError(f"{file}: projectors.{name}: expected {len(levels)} frame files "
                              f"(one per level)")
        try:
            images = [load_grey(root / rel, f"grey ramp of projector {name}, level {lv}")
                      for rel, lv in zip(files, levels, strict=True)]
            out[name] = measure_response(images, levels)
        except (CalibrationError, FrameError) as exc:
            out[name] = str(exc)
    return out


def gamma_lines(results: dict[str, Response | str] | None) -> list[str]:
    """Plain lines for the report: the fitted gamma of each projector, with advice."""
    if results is None:
        return [f"projector gamma: not measured (the session has no {RAMP_DIR}/ folder)"]
    lines = []
    for name, r in results.items():
        if isinstance(r, str):
            lines.append(f"projector {name}: gamma not measured: {r}")
            continue
        mid = float(np.interp(128, r.levels[np.argsort(r.levels)],
                              r.response[np.argsort(r.levels)]))
        lines.append(f"projector {name}: gamma {r.gamma:.2f} (fit RMS {r.rms:.4f} over "
                     f"{len(r.levels)} grey levels; grey 128 gives {100 * mid:.0f} % of white)")
        if abs(r.gamma - 1) > NONLINEAR_TOLERANCE:
            lines.append(
                f"  note: projector {name} is not linear: the camera sees grey 128 at "
                f"{100 * mid:.0f} % of white instead of 50 %, so the soft edges of projected "
                f"lines come out sharper than drawn.  If the projector has a linear, 'raw' "
                f"or gamma 1.0 picture mode, select it and measure again."
            )
    return lines
