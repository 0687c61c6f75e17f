"""A one-line terminal status of a run, and the summary printed at its end.

On a terminal the line is rewritten in place (``\\r``) at most a few times a
second; when stderr is a file or a pipe (CI logs, ``2> log``) a full line is
printed every few seconds instead, so logs stay readable.

Two shares of pixels with a depth, named apart everywhere (status line,
summary, Rerun, eval):

depth on image
    Of all camera pixels, the share that got a depth in the last frame.  Known
    in every run (``FrameResult.coverage``).
coverage
    Of the pixels on a moving object that every projector lights, the share
    that got a depth.  Needs ground truth (simulated recordings): ``lightflow
    eval``, the demo's accuracy line, and Rerun's green coverage series.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections.abc import Iterable
from typing import TextIO

from lightflow.app.core.results import RunStats

TTY_INTERVAL_S = 0.2
LOG_INTERVAL_S = 5.0
#: the name of ``stats.extra["coverage"]`` (``FrameResult.coverage``) wherever it is shown
DEPTH_ON_IMAGE = "depth on image"
#: camera statistics worth showing, as (key in stats.extra, label)
CAMERA_FIELDS = (
    ("camera_underruns", "underruns"),
    ("camera_failures", "failures"),
    ("camera_missing_packets", "missing packets"),
    ("camera_missing_frames", "missing frames"),
    ("camera_bad_buffers", "bad buffers"),
    ("camera_dropped_in_driver", "dropped by the driver (consumer too slow)"),
    ("camera_discarded_at_stop", "not taken at stop"),
)


def format_status(stats: RunStats, total: int | None = None) -> str:
    """The status line text (no newline), e.g. ``frame 12/40  29.8 fps  ...``."""
    done = f"frame {stats.frames_done}/{total}" if total else f"{stats.frames_done} frames"
    # no rate yet (see RateMeter): a dash, not a number
    rate = f"{stats.mib_per_s:6.1f}" if stats.mib_per_s > 0 else "     –"
    parts = [done, f"{stats.fps:5.1f} fps", f"{rate} MiB/s"]
    parts.append(f"latency {stats.latency_ms:4.0f} ms")
    if "coverage" in stats.extra:
        # not eval's "coverage" (moving lit pixels with depth): see the module docstring
        parts.append(f"{DEPTH_ON_IMAGE} {100 * stats.extra['coverage']:3.0f}%")
    e = stats.extra
    parts.append(
        f"drops {int(e.get('dropped_frames_queue', 0))} frames/"
        f"{int(e.get('dropped_results_queue', 0))} results"
    )
    if e.get("recorder_dropped"):
        parts.append(f"recorder dropped {int(e['recorder_dropped'])}")
    if stats.camera_lost:
        parts.append(f"camera lost {stats.camera_lost}")
    for key, label in CAMERA_FIELDS:
        if key in e:
            parts.append(f"{label} {int(e[key])}")
    return "  ".join(parts)


def format_summary(
    stats: RunStats, bad_frames: Iterable[str] = (), elapsed_s: float | None = None
) -> list[str]:
    """The end-of-run summary lines: processed, dropped, lost and bad frames."""
    bad = list(bad_frames)
    rate = f" in {elapsed_s:.1f} s" if elapsed_s else ""
    lines = [
        f"processed {stats.frames_done} of {stats.frames_in} frames{rate}; "
        f"dropped {stats.dropped} (frames queue "
        f"{int(stats.extra.get('dropped_frames_queue', 0))}, results queue "
        f"{int(stats.extra.get('dropped_results_queue', 0))}); "
        f"lost by the camera {stats.camera_lost}; bad frames {len(bad)}"
    ]
    if "coverage" in stats.extra:
        lines.append(
            f"{DEPTH_ON_IMAGE} (share of all camera pixels with a depth, last frame): "
            f"{100 * stats.extra['coverage']:.1f}%"
        )
    causes = no_depth_counts(stats.extra)
    if causes is not None and causes.sum():
        from .core.causes import describe_counts

        lines.append(
            f"no depth, by cause (share of all analysis-grid pixels, whole run): "
            f"{describe_counts(causes, top=6)}"
        )
    if stats.extra.get("leak_unknown_frames"):
        lines.append(
            f"colour leak unknown on {int(stats.extra['leak_unknown_frames'])} frame(s) "
            f"(no clean gaps between the patterns yet): taken as 0 there"
        )
    for key, label in CAMERA_FIELDS:
        if stats.extra.get(key):
            lines.append(f"camera {label}: {int(stats.extra[key])}")
    if bad:
        lines.append(f"{len(bad)} bad frame(s) skipped:")
        lines.extend(f"  {line}" for line in bad)
    return lines


#: where the depth pipeline's lens blur came from (``FlowModel.blur_source``), for the summary
BLUR_SOURCES = {
    "rig": "measured, from the rig file",
    "still lines": "measured on lines that stood still between the first frames (a wall)",
    "moving bands": "fitted on the moving bands: `lightflow rig blur` (a board held still at "
                    "three depths) measures it, and fans and balls then get 2-4x more depth",
    "": "not known (no frame had enough bands)",
}


#: a live run whose depth skipped more than this share of the frames gets a hint
SKIPPED_HINT = 0.1


def describe_speed(stats: RunStats, stride: int) -> str | None:
    """A hint for a live run whose depth could not keep up with the camera, or None.

    Parameters
    ----------
    stats : RunStats
        The run's final statistics: the frames the pipeline skipped are those dropped
        from its input queue (``extra["dropped_frames_queue"]``; results or outputs
        dropped later are an output's slowness, not the pipeline's).
    stride : int
        The analysis grid stride the run used.
    """
    skipped = int(stats.extra.get("dropped_frames_queue", 0))
    if not stats.frames_in or skipped <= SKIPPED_HINT * stats.frames_in:
        return None
    text = (f"depth kept up with {stats.frames_in - skipped} of {stats.frames_in} frames "
            f"(the pipeline skipped the others, counted above as the frames queue's)")  # fmt: skip
    if stride < 8:
        text += (f"; --stride 8 takes about half the CPU of stride {stride} per frame, for "
                 "the same accuracy and a little less coverage (see --help)")  # fmt: skip
    return text


def describe_blur(pipeline) -> str:
    """One summary line: the lens blur the pipeline used and where it came from.

    Short sweeps (fans at 1 ms, balls at 5 ms) count only against a measured
    blur, so a run without one says how to measure it.
    """
    fm = pipeline.flow_model
    sigmas = [f"{s:.2f}" for s in fm.blur_px if math.isfinite(s)]
    size = f" (sigma {' and '.join(sigmas)} camera px)" if sigmas else ""
    return f"lens blur{size}: {BLUR_SOURCES.get(fm.blur_source, fm.blur_source)}"


def describe_response(pipeline) -> str:
    """One summary line: the camera response the frames were linearised with, and whence.

    A camera that is not linear reads every band wide and the depth long, so a
    run whose rig does not say says how to measure it.
    """
    gamma = pipeline.camera_gamma
    source = {"option": "from --camera-gamma", "rig": "from the rig file",
              "still lines": f"measured {pipeline.gamma_measured:.3f} on lines that stood "
                             f"still between the first frames (a wall)"}.get(pipeline.gamma_source)
    if source is None:
        why = ("no lines stood still to measure it on" if not pipeline.gamma_source
               else "the rig file gives no camera.gamma")
        return (f"camera response: taken as linear ({why}): a webcam or an sRGB image reads "
                f"every depth long; `lightflow rig blur` measures it")
    if gamma != 1.0:
        return f"camera response: gamma {gamma:g} ({source}): frames linearised"
    return f"camera response: linear ({source})"


def crosstalk_shares(rig, values) -> str:
    """``values`` (per pattern) said in words: "the red channel sees 4.0 % of the blue
    light and the blue channel sees 3.0 % of the red light"."""
    a, b = (pat.channel for _, pat in rig.patterns)
    return " and ".join(
        f"the {name} channel sees {100 * v:.1f} % of the {other} light" if math.isfinite(v)
        else f"not known for the {name} channel"
        for v, name, other in ((values[0], a, b), (values[1], b, a))
    )


def describe_crosstalk(pipeline) -> str:
    """One summary line: the colour crosstalk subtracted from the frames, and whence.

    Estimated on the frames it needs clean gaps between the bands, which long sweeps
    and dense patterns do not leave, so a run whose rig does not give it says how to
    measure it.
    """
    values, source = pipeline.crosstalk
    shares = crosstalk_shares(pipeline.rig, values)
    if source == "option":
        return f"colour crosstalk: {shares} (from the crosstalk option)"
    if source == "rig":
        return f"colour crosstalk: {shares} (measured, from the rig file)"
    how = "`lightflow rig blur` measures it on still lines"
    if source == "frames":
        return f"colour crosstalk: {shares} (estimated on the frames; {how})"
    return f"colour crosstalk: not known (no frame gave an estimate; taken as 0; {how})"


#: ``RunStats.extra`` key prefix of the grid pixels without depth, summed over a run
CAUSE_PREFIX = "no_depth:"


def no_depth_counts(extra: dict):
    """Grid pixels per cause code summed over a run (``None`` before the first frame)."""
    import numpy as np

    from .core.causes import CAUSE_NAMES

    if CAUSE_PREFIX + CAUSE_NAMES[0] not in extra:
        return None
    return np.array([extra.get(CAUSE_PREFIX + name, 0.0) for name in CAUSE_NAMES])


class StatusLine:
    """Shows :class:`RunStats` on one terminal line; thread-safe, throttles itself.

    Parameters
    ----------
    stream : file, optional
        Default ``sys.stderr``.
    total : int, optional
        Expected number of frames (shown as ``frame i/n``).
    interval_s : float, optional
        Minimum time between updates (default 0.2 s on a terminal, 5 s otherwise).
    """

    def __init__(
        self,
        stream: TextIO | None = None,
        total: int | None = None,
        interval_s: float | None = None,
    ):
        self.stream = stream if stream is not None else sys.stderr
        try:
            self.tty = self.stream.isatty()
        except (AttributeError, ValueError):
            self.tty = False
        self.total = total
        self.interval_s = interval_s if interval_s is not None else (
            TTY_INTERVAL_S if self.tty else LOG_INTERVAL_S
        )
        self._next = 0.0
        self._width = 0
        self._lock = threading.Lock()
        self._t0 = time.perf_counter()
        self.last: RunStats | None = None

    def update(self, stats: RunStats, force: bool = False) -> None:
        """Show ``stats`` if the last update is old enough (or ``force``)."""
        now = time.perf_counter()
        with self._lock:
            self.last = stats
            if not force and now < self._next:
                return
            self._next = now + self.interval_s
            text = format_status(stats, self.total)
            if self.tty:
                pad = max(0, self._width - len(text))
                self.stream.write("\r" + text + " " * pad)
                self._width = len(text)
            else:
                self.stream.write(text + "\n")
            self.stream.flush()

    __call__ = update

    def message(self, text: str) -> None:
        """Print a full line without garbling the status line."""
        with self._lock:
            if self.tty and self._width:
                self.stream.write("\r" + " " * self._width + "\r")
                self._width = 0
                self._next = 0.0
            self.stream.write(text + "\n")
            self.stream.flush()

    def finish(self, stats: RunStats, bad_frames: Iterable[str] = ()) -> None:
        """End the status line and print the summary."""
        with self._lock:
            if self.tty and self._width:
                self.stream.write("\n")
                self._width = 0
            elapsed = time.perf_counter() - self._t0
            for line in format_summary(stats, bad_frames, elapsed):
                self.stream.write(line + "\n")
            self.stream.flush()


def is_terminal(stream) -> bool:
    """Whether ``stream`` is a terminal (progress rewrites one line in place there)."""
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


class Progress:
    """``progress(done, total)`` callback printing a percentage (e.g. while a LUT is built).

    On a terminal the line is rewritten in place; otherwise one line per 25 %.
    """

    def __init__(self, label: str, stream: TextIO | None = None):
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.tty = is_terminal(self.stream)
        self._shown = -1
        self._started = False

    def __call__(self, done: float, total: float) -> None:
        pct = int(100 * done / total) if total else 100
        step = 1 if self.tty else 25
        if pct // step == self._shown // step and pct != 100:
            return
        if pct == self._shown:
            return
        if not self._started:
            self._started = True
            if not self.tty:
                self.stream.write(f"{self.label} ...\n")
        self._shown = pct
        if self.tty:
            self.stream.write(f"\r{self.label}: {pct:3d}%")
            if pct >= 100:
                self.stream.write("\n")
        else:
            self.stream.write(f"{self.label}: {pct}%\n")
        self.stream.flush()
