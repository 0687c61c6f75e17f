"""The simulator's own reading of a rig, from the rig format (docs/formats.md, section 1).

The reconstruction parses rig files with :mod:`lightflow.app.core.rig`.  The
simulator reads the same document itself, into plain arrays, so that a
mistake in the core's reading (an axis, a transposition, a pattern
parameter) renders a different scene from the one the core reconstructs,
and shows in the evaluation instead of cancelling.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: colour channel of a pattern, as the format names it, to the RGB index
CHANNELS = {"red": 0, "green": 1, "blue": 2}


@dataclass(frozen=True)
class SimCamera:
    """Pinhole camera with OpenCV distortion, as the rig document gives it."""

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray


@dataclass(frozen=True)
class SimProjector:
    """A projector: ``X_projector = R X_camera + t`` (metres)."""

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray

    @property
    def centre(self) -> np.ndarray:
        """Centre of projection in camera coordinates."""
        return -self.R.T @ self.t


@dataclass(frozen=True)
class SimPattern:
    """One line pattern: which projector shows it, in which channel, and its lines.

    ``on_level`` and ``off_level`` are the 8-bit levels of its lit and its dark
    columns.  The rig format's patterns are binary (255 and 0); other levels
    describe patterns the format cannot express, which the renderer passes
    through the projector's response like any level.
    """

    projector: int
    channel: int
    kind: str
    width_px: float
    pitch_px: float = 0.0
    offset_px: float = 0.0
    lines: int = 0
    on_level: int = 255
    off_level: int = 0


@dataclass(frozen=True)
class SimRig:
    """Camera, projectors and patterns in file order."""

    camera: SimCamera
    projectors: tuple[SimProjector, ...]
    patterns: tuple[SimPattern, ...]


def read_rig(doc: dict) -> SimRig:
    """Read a rig document (already checked by the core's reader) into plain arrays.

    Parameters
    ----------
    doc : dict
        The rig as its JSON document (``Rig.to_dict()`` or a parsed rig file).

    Returns
    -------
    SimRig
    """
    cam = doc["camera"]
    camera = SimCamera(int(cam["width"]), int(cam["height"]),
                       np.array(cam["K"], dtype=np.float64).reshape(3, 3),
                       np.array(cam.get("dist", []), dtype=np.float64))  # fmt: skip
    projectors, patterns = [], []
    for i, p in enumerate(doc["projectors"]):
        projectors.append(SimProjector(
            int(p["width"]), int(p["height"]),
            np.array(p["K"], dtype=np.float64).reshape(3, 3),
            np.array(p.get("dist", []), dtype=np.float64),
            np.array(p["R"], dtype=np.float64).reshape(3, 3),
            np.array(p["t"], dtype=np.float64).reshape(3),
        ))  # fmt: skip
        for pat in p["patterns"]:
            kind = pat.get("kind", "uniform")
            patterns.append(SimPattern(
                projector=i, channel=CHANNELS[pat["channel"]], kind=kind,
                width_px=float(pat["width_px"]),
                pitch_px=float(pat.get("pitch_px", 0.0)),
                offset_px=float(pat.get("offset_px", 0.0)),
                lines=int(pat.get("lines", 0)),
            ))  # fmt: skip
    return SimRig(camera, tuple(projectors), tuple(patterns))
