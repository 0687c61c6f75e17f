"""A recording (formats.md section 2) replayed as a camera.

Bad frames (missing, unreadable, wrong size) do not end a replay: they are
skipped and listed in :attr:`RecordedCamera.bad_frames`, one line each, so a
partly damaged recording still yields every good frame and the user learns
exactly which files to look at.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator
from pathlib import Path

from lightflow.app.errors import DriverError, FrameError
from lightflow.app.recording import Recording, load_frame, read_recording
from lightflow.app.rig import Rig
from lightflow.drivers.base import Camera, Frame


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
    """

    def __init__(
        self,
        path: str | Path,
        rig: Rig | None = None,
        loop: bool = False,
        realtime: bool = False,
    ):
        self.recording: Recording = read_recording(path, rig)
        self.rig: Rig = self.recording.rig
        self.uri = f"replay:{path}"
        self.loop = loop
        self.realtime = realtime
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
        lap = 0
        while True:
            good = 0
            for i, entry in enumerate(entries):
                if self._stop.is_set():
                    return
                try:
                    image = load_frame(self.recording, i)
                except FrameError as exc:
                    if lap == 0:
                        self.bad_frames.append(str(exc))
                    continue
                good += 1
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
            lap += 1
            if not self.loop or good == 0:
                return
