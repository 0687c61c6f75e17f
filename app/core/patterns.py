"""Line patterns exactly as formats.md defines them (numpy; the pitch also for numba).

Line k covers the projector columns x with ``|x - u_k| <= width_px / 2``.
Because a projector lights whole pixels, the light of line k physically spans
``[first_lit - 0.5, last_lit + 0.5]``; :func:`line_footprints` gives these.

For flow measurement every pattern has a continuous *line index* k(u): the
lines sit at integer k, so a band's sweep divided by the local line interval
is a flow in index units.  ``local_pitch(u)`` (the numba kernels: ``pitch_at``)
converts it to projector pixels.
"""

from __future__ import annotations

import math

import numpy as np
from numba.extending import register_jitable

from .rig import CHANNEL_INDEX, Pattern, ProjectorModel


def line_centres(pattern: Pattern, width: int) -> np.ndarray:
    """Nominal centres ``u_k`` of the lines, in projector pixels."""
    if pattern.kind == "uniform":
        n = math.floor((width - 1e-9 - pattern.offset_px) / pattern.pitch_px) + 1
        return pattern.offset_px + np.arange(n) * pattern.pitch_px
    n = pattern.lines
    if pattern.kind == "exp2":
        k = np.arange(0, n)
        return width * (2.0 ** (k / n) - 1)
    k = np.arange(1, n + 1)
    return width * (2 - 2.0 ** (1 - k / n))


def line_columns(pattern: Pattern, width: int) -> np.ndarray:
    """``(n, 2)`` int: the first and last whole column each line covers,
    ``|x - u_k| <= width_px / 2``, before clipping to the projector's ``width``."""
    u = line_centres(pattern, width)
    half = pattern.width_px / 2
    lo = np.ceil(u - half - 1e-9).astype(np.int64)
    hi = np.floor(u + half + 1e-9).astype(np.int64)
    return np.stack([lo, hi], axis=1)


def lit_columns(pattern: Pattern, width: int) -> np.ndarray:
    """Boolean ``(width,)``: which projector columns the pattern lights."""
    lit = np.zeros(width, dtype=bool)
    for lo, hi in line_columns(pattern, width):
        lo, hi = max(0, lo), min(width - 1, hi)
        if hi >= lo:
            lit[lo : hi + 1] = True
    return lit


def line_footprints(pattern: Pattern, width: int) -> np.ndarray:
    """``(n, 2)`` continuous column intervals physically lit by each line."""
    lit = lit_columns(pattern, width).astype(np.int8)
    edges = np.diff(np.concatenate([[0], lit, [0]]))
    starts = np.flatnonzero(edges == 1)
    ends = np.flatnonzero(edges == -1) - 1
    return np.stack([starts - 0.5, ends + 0.5], axis=1).astype(np.float64)


def pattern_image(projector: ProjectorModel) -> np.ndarray:
    """The RGB ``uint8`` image ``(height, width, 3)`` this projector shows."""
    img = np.zeros((projector.height, projector.width, 3), dtype=np.uint8)
    for pat in projector.patterns:
        cols = lit_columns(pat, projector.width)
        img[:, cols, CHANNEL_INDEX[pat.channel]] = 255
    return img


def exp2_step(pattern: Pattern) -> float:
    """Local pitch of an exp2 pattern per unit of ``u + W`` (projector px).

    The symmetric difference ``(u_{k+1} - u_{k-1}) / 2`` of the exp2 series of
    line positions, divided by ``u + W``: constant along the pattern.
    """
    return (2 ** (1 / pattern.lines) - 2 ** (-1 / pattern.lines)) / 2


#: kind codes of :func:`pattern_code` (numba kernels take numbers, not strings)
KIND_CODE = {"uniform": 0, "exp2": 1, "exp2-reversed": 2}


def pattern_code(pattern: Pattern) -> tuple[int, float]:
    """``(kind code, step)`` of a pattern for :func:`pitch_at`.

    The step is the pitch of a uniform pattern and :func:`exp2_step` of the others.
    """
    code = KIND_CODE[pattern.kind]
    return code, float(pattern.pitch_px if code == 0 else exp2_step(pattern))


@register_jitable
def pitch_at(code, step, width, u):
    """Local line interval (projector px) at column ``u``: the one pitch formula.

    Parameters
    ----------
    code, step : int, float
        From :func:`pattern_code`.
    width : float
        Projector width W in pixels.
    u : float or numpy.ndarray
        Projector column (a scalar in numba kernels, which compile this in).

    Returns
    -------
    float or numpy.ndarray
        ``step`` for uniform patterns (a scalar); ``(u + W) step`` for exp2 and
        ``(2 W - u) step`` for exp2-reversed, the exact symmetric difference
        ``(u_{k+1} - u_{k-1}) / 2`` at a line ``u_k``.
    """
    if code == 0:
        return step
    if code == 1:
        return (u + width) * step
    return (2.0 * width - u) * step


def local_pitch(pattern: Pattern, width: int, u):
    """Local line interval in projector pixels at column ``u`` (:func:`pitch_at` on arrays).

    For exp2 patterns this is the exact symmetric difference
    ``(u_{k+1} - u_{k-1}) / 2`` at a line ``u_k``, which is linear in ``u``.
    """
    u = np.asarray(u, dtype=np.float64)
    code, step = pattern_code(pattern)
    return np.broadcast_to(pitch_at(code, step, width, u), u.shape).copy()


def line_index(pattern: Pattern, width: int, u):
    """Continuous line index k(u) (integers at the line centres)."""
    u = np.asarray(u, dtype=np.float64)
    if pattern.kind == "uniform":
        return (u - pattern.offset_px) / pattern.pitch_px
    n = pattern.lines
    with np.errstate(divide="ignore", invalid="ignore"):
        if pattern.kind == "exp2":
            return n * np.log2(u / width + 1)
        return n * (1 - np.log2(2 - u / width))
