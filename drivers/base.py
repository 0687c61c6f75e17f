"""The two small device interfaces: :class:`Camera` and :class:`PatternOutput`.

Every camera (Aravis, V4L2, synthetic, recorded replay) implements
:class:`Camera` as an equal.  The capture loop only ever sees this interface.

Buffer lifetime: the ``image`` of a yielded :class:`Frame` belongs to the
consumer; a driver never reuses it after yielding (drivers that stream into
pooled buffers copy out before yielding, as harvesters does).
"""

from __future__ import annotations

import abc
import collections
import threading
from collections.abc import Iterator

from lightflow.app.core.frame import Frame


class Camera(abc.ABC):
    """A camera: open/close, exposure, image size, and a frame iterator.

    Use as a context manager::

        with camera:
            camera.set_exposure(0.02)
            for frame in camera.frames():
                ...

    ``frames()`` ends when the source is exhausted (replay, synthetic) or when
    :meth:`stop` is called from another thread; a lost device raises
    :class:`~lightflow.app.core.errors.DeviceLostError`.
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
        from lightflow.app.core.errors import DriverError

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


class FrameHandoff:
    """What a camera's acquisition thread hands its consumer: copied-out frames, capped in bytes.

    The acquisition thread :meth:`put`\\ s items (tuples whose element 1 is the
    frame's bytes) and ends with :meth:`finish`; past ``max_bytes`` the oldest
    item is dropped and counted (``dropped``).  The consumer :meth:`get`\\ s the
    next item: ``None`` when the stream ended or ``stop`` is set (what was still
    waiting is then counted in ``discarded``), and the acquisition thread's
    error is raised there, on the consumer's thread.

    Parameters
    ----------
    max_bytes : float
        Memory cap of the waiting frames.
    """

    def __init__(self, max_bytes: float):
        self.max_bytes = max_bytes
        self._items: collections.deque = collections.deque()
        self._bytes = 0
        self._cond = threading.Condition()
        self._done = False
        self._error: BaseException | None = None
        self.dropped = 0
        self.discarded = 0

    def put(self, item: tuple) -> None:
        """Add a frame (acquisition thread); drop the oldest past the cap."""
        with self._cond:
            self._items.append(item)
            self._bytes += len(item[1])
            while self._bytes > self.max_bytes and len(self._items) > 1:
                self._bytes -= len(self._items.popleft()[1])
                self.dropped += 1
            self._cond.notify_all()

    def finish(self, error: BaseException | None = None) -> None:
        """The stream ended (acquisition thread), with ``error`` for the consumer if any."""
        with self._cond:
            if error is not None:
                self._error = error
            self._done = True
            self._cond.notify_all()

    def wake(self) -> None:
        """Wake a waiting :meth:`get` (after setting its ``stop`` event)."""
        with self._cond:
            self._cond.notify_all()

    def get(self, stop: threading.Event) -> tuple | None:
        """The next frame, waiting for it; ``None`` at the end or once ``stop`` is set."""
        with self._cond:
            while not self._items and not self._done and not stop.is_set():
                self._cond.wait()
            if stop.is_set():
                self._discard()  # stop() ends the stream now; what waited is counted
                return None
            if self._items:
                item = self._items.popleft()
                self._bytes -= len(item[1])
                return item
            if self._error is not None:
                error, self._error = self._error, None
                raise error
            return None

    def discard(self) -> None:
        """Drop what is still waiting, counted in ``discarded`` (the stream is over)."""
        with self._cond:
            self._discard()

    def _discard(self) -> None:
        self.discarded += len(self._items)
        self._items.clear()
        self._bytes = 0
