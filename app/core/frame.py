"""One exposure from a camera: the core's frame type, shared with the drivers."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Frame:
    """One exposure from a camera.

    Attributes
    ----------
    index : int
        Sequence number given by the camera.  A gap between consecutive
        indices means the camera (or the transport) lost frames.
    timestamp : float
        Start of the exposure in seconds (camera clock, or recording time).
    exposure_s : float
        Exposure length in seconds.
    image : numpy.ndarray
        ``(height, width, 3)`` RGB image, ``uint8`` or ``uint16``.
    name : str
        Stem used for exported files (``000012``).
    extras : dict
        Driver-specific data, e.g. ``{"truth": GroundTruth}`` from the synthetic camera.
    bits : int, optional
        Significant bits per sample (a 12-bit camera gives ``uint16`` values
        0..4095: full scale is ``2**bits - 1``).  None: the dtype's full range.
    """

    index: int
    timestamp: float
    exposure_s: float
    image: np.ndarray
    name: str = ""
    extras: dict[str, Any] = field(default_factory=dict)
    bits: int | None = None

    @property
    def stem(self) -> str:
        return self.name or f"{self.index:06d}"

    @property
    def full_scale(self) -> float:
        """The sample value of full exposure: ``2**bits - 1``, or the dtype's maximum."""
        if self.bits:
            return float(2**self.bits - 1)
        return 65535.0 if self.image.dtype == np.uint16 else 255.0
