"""A recording (formats.md section 2) replayed as a camera.

Bad frames (missing, unreadable, wrong size) do not end a replay: they are
skipped and listed in :attr:`RecordedCamera.bad_frames`, one line each, so a
partly damaged recording still yields every good frame and the user learns
exactly which files to look at.

Frames are decoded ahead on a reader thread (PNG decoding releases the GIL),
at most :data:`READ_AHEAD` of them waiting, so the pipeline does not wait on
file I/O once it is warm; they are still yielded in the recording's order.
"""

from __future__ import annotations

import collections
import math
import threading
import time
from collections.abc import Iterator
from pathlib import Path

from lightflow.app.core.errors import DriverError, FrameError
from lightflow.app.core.rig import Rig
from lightflow.app.recording import Recording, load_frame, read_recording
from lightflow.drivers.base import Camera, Frame

#: decoded frames kept ready by the reader thread (a 1600x1200 RGB frame is 5.5 MiB)
READ_AHEAD = 4


class RecordedCamera(Camera):
    """Replay a recording folder as a :class:`Camera`.

    Parameters
    ----------
    path : str or Path
        The recording folder.
    rig : Rig, optional
        Overrides the rig embedded in the recording (frames are checked against its camera).
    loop : bool
        Start over at the end (timestamps and indices keep increasing).
    realtime : bool
        Pace frames by their recorded timestamps instead of as fast as possible.
    read_ahead : int
        Frames decoded ahead on a reader thread (0: decode on the caller's thread).
    """

    def __init__(
        self,
        path: str | Path,
        rig: Rig | None = None,
        loop: bool = False,
        realtime: bool = False,
        read_ahead: int = READ_AHEAD,
    ):
        self.recording: Recording = read_recording(path, rig)
        self.rig: Rig = self.recording.rig
        self.uri = f"replay:{path}"
        self.loop = loop
        self.realtime = realtime
        self.read_ahead = max(0, int(read_ahead))
        #: one line per frame that could not be replayed
        self.bad_frames: list[str] = []
        self._stop = threading.Event()
        self._delivered = 0

    def open(self) -> None:
        self._stop.clear()

    def close(self) -> None:
        self._stop.set()

    @property
    def size(self) -> tuple[int, int]:
        cam = self.rig.camera
        return cam.width, cam.height

    @property
    def exposure_s(self) -> float:
        return self.recording.exposure_s

    def set_exposure(self, seconds: float) -> float:
        """Accept only the recorded exposure: a recording's exposure is fixed."""
        if not math.isclose(seconds, self.exposure_s, rel_tol=1e-6, abs_tol=1e-9):
            raise DriverError(
                f"{self.uri}: a recording's exposure is fixed at {self.exposure_s * 1e3:g} ms, "
                f"cannot set {seconds * 1e3:g} ms"
            )
        return self.exposure_s

    def stop(self) -> None:
        self._stop.set()

    def stats(self) -> dict[str, float]:
        return {"delivered": float(self._delivered), "bad_frames": float(len(self.bad_frames))}

    def frames(self) -> Iterator[Frame]:
        """Yield the good frames in order; collect the bad ones in :attr:`bad_frames`."""
        entries = self.recording.frames
        if not entries:
            return
        t0 = entries[0].t
        # one lap lasts from the first exposure start to one frame period after the last
        period = (entries[-1].t - t0) / (len(entries) - 1) if len(entries) > 1 else 0.0
        lap_s = entries[-1].t - t0 + (period or self.exposure_s)
        wall0 = time.perf_counter()
        for lap, i, image in self._decoded():
            if self._stop.is_set():
                return  # stop() ends the stream at once, decoded frames or not
            entry = entries[i]
            rel_t = entry.t - t0 + lap * lap_s
            if self.realtime:
                delay = wall0 + rel_t - time.perf_counter()
                # Event.wait: paces like a camera and still ends at once on stop()
                if delay > 0 and self._stop.wait(delay):
                    return
            self._delivered += 1
            yield Frame(
                index=lap * len(entries) + i,
                timestamp=entry.t + lap * lap_s,
                exposure_s=self.exposure_s,
                image=image,
                name=entry.stem,
                bits=self.recording.bits,
            )

    def _decode_all(self, halt: threading.Event) -> Iterator[tuple[int, int, object]]:
        """(lap, index, image) of every good frame, in order; bad ones go to :attr:`bad_frames`."""
        entries = self.recording.frames
        lap = 0
        while True:
            good = 0
            for i in range(len(entries)):
                if self._stop.is_set() or halt.is_set():
                    return
                try:
                    image = load_frame(self.recording, i)
                except FrameError as exc:
                    if lap == 0:
                        self.bad_frames.append(str(exc))
                    continue
                good += 1
                yield lap, i, image
            lap += 1
            if not self.loop or good == 0:
                return

    def _decoded(self) -> Iterator[tuple[int, int, object]]:
        """:meth:`_decode_all`, run on a reader thread :attr:`read_ahead` frames ahead."""
        halt = threading.Event()
        if self.read_ahead == 0:
            yield from self._decode_all(halt)
            return
        items: collections.deque = collections.deque()
        cond = threading.Condition()
        done: list[BaseException | None] = []  # [error or None] once the reader ended

        def read() -> None:
            error = None
            try:
                for item in self._decode_all(halt):
                    with cond:
                        while len(items) >= self.read_ahead and not halt.is_set():
                            cond.wait()
                        if halt.is_set():
                            return
                        items.append(item)
                        cond.notify_all()
            except BaseException as exc:  # noqa: BLE001 - re-raised on the consumer's thread
                error = exc
            finally:
                with cond:
                    done.append(error)
                    cond.notify_all()

        reader = threading.Thread(target=read, name="lightflow-replay-reader", daemon=True)
        reader.start()
        try:
            while True:
                with cond:
                    while not items and not done:
                        cond.wait()
                    if items:
                        item = items.popleft()
                        cond.notify_all()
                    elif done[0] is not None:
                        raise done[0]
                    else:
                        return
                yield item
        finally:
            # the consumer ended (or stopped early): release and wait for the reader
            with cond:
                halt.set()
                cond.notify_all()
            reader.join()
