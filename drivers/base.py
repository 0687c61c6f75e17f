"""The two small device interfaces: :class:`Camera` and :class:`PatternOutput`.

Every camera (Aravis, V4L2, synthetic, recorded replay) implements
:class:`Camera` as an equal.  The capture loop only ever sees this interface.

Buffer lifetime: the ``image`` of a yielded :class:`Frame` belongs to the
consumer; a driver never reuses it after yielding (drivers that stream into
pooled buffers copy out before yielding, as harvesters does).
"""

from __future__ import annotations

import abc
from collections.abc import Iterator
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


class Camera(abc.ABC):
    """A camera: open/close, exposure, image size, and a frame iterator.

    Use as a context manager::

        with camera:
            camera.set_exposure(0.02)
            for frame in camera.frames():
                ...

    ``frames()`` ends when the source is exhausted (replay, synthetic) or when
    :meth:`stop` is called from another thread; a lost device raises
    :class:`~lightflow.app.errors.DeviceLostError`.
    """

    #: a short URI-like description, e.g. ``aravis:127.0.0.1``
    uri: str = ""

    @abc.abstractmethod
    def open(self) -> None:
        """Acquire the device.  Raises DriverError with the device name on failure."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the device.  Safe to call twice."""

    @property
    @abc.abstractmethod
    def size(self) -> tuple[int, int]:
        """Image size as ``(width, height)``."""

    def set_size(self, width: int, height: int) -> None:
        """Set the image size; the default accepts only the current size."""
        from lightflow.app.errors import DriverError

        if (width, height) != self.size:
            w, h = self.size
            raise DriverError(
                f"{self.uri}: camera image is {w}x{h}, the rig needs {width}x{height}"
            )

    @property
    @abc.abstractmethod
    def exposure_s(self) -> float:
        """Current exposure time in seconds (read back from the device)."""

    @abc.abstractmethod
    def set_exposure(self, seconds: float) -> float:
        """Set the exposure time and return the value the device actually uses."""

    @abc.abstractmethod
    def frames(self) -> Iterator[Frame]:
        """Yield frames until exhausted or stopped."""

    def stop(self) -> None:  # noqa: B027 - optional hook
        """Ask a running :meth:`frames` iterator to end soon (thread-safe)."""

    def stats(self) -> dict[str, float]:
        """Transport statistics (completed, failures, underruns, ...); empty by default."""
        return {}

    def __enter__(self) -> Camera:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class PatternOutput(abc.ABC):
    """Shows the rig's pattern images on projectors.

    Implementations that own a GUI toolkit run on the main thread; see
    :mod:`lightflow.drivers.projector`.
    """

    @abc.abstractmethod
    def open(self) -> None:
        """Create the outputs (e.g. fullscreen windows) and show the patterns."""

    @abc.abstractmethod
    def close(self) -> None:
        """Remove the outputs."""

    def __enter__(self) -> PatternOutput:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()
