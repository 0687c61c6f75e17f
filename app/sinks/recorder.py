"""A sink that records the input frames of a run as a replayable recording."""

from __future__ import annotations

from pathlib import Path

from lightflow.app.core.results import FrameResult, RunStats
from lightflow.app.core.rig import Rig
from lightflow.app.recording import RecordingWriter


class RecorderSink:
    """Write ``result.frame`` of every result into a recording folder (formats.md section 2).

    Parameters
    ----------
    root : str or Path
        New recording folder.
    rig : Rig
        Embedded in the recording.
    exposure_s : float
        The camera's exposure.
    """

    def __init__(self, root: str | Path, rig: Rig, exposure_s: float, **writer_options):
        self.writer = RecordingWriter(root, rig, exposure_s, **writer_options)

    def write(self, result: FrameResult, stats: RunStats) -> None:
        self.writer.write(result.frame)
        stats.extra["recorder_dropped"] = float(self.writer.dropped)

    def close(self) -> None:
        self.writer.close()

    def describe(self) -> str:
        w = self.writer
        dropped = f", {w.dropped} DROPPED (disk too slow)" if w.dropped else ""
        return (
            f"recording: {w.written} frames in {w.root}/{dropped}; "
            f"check it with `lightflow verify {w.root}`"
        )
