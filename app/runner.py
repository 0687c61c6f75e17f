"""The run loop: camera -> depth pipeline -> sinks, on three worker threads.

::

    capture thread ──frames──▶ processing thread ──results──▶ sink thread
    (owns the camera)  queue   (owns the pipeline)   queue   (owns the sinks)

Each resource has one owning thread.  The queues are bounded: in live mode a
full queue drops its *oldest* item (a live view wants the newest frame) and
counts the drop; in lossless mode (offline replay and evaluation) a full
queue blocks the producer instead, so no frame is ever lost.

Errors: the first exception of any worker is stored and re-raised from
:meth:`Runner.join` unchanged (a :class:`~lightflow.app.core.errors.LightflowError`
stays a one-line message).  Whatever fails, the sink thread writes what
already reached it and closes every sink exactly once, so a recording of a
camera that was unplugged mid-stream stays complete and replayable.
"""

from __future__ import annotations

import collections
import copy
import gc
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

from lightflow.app.core.errors import OutputClosed
from lightflow.app.core.results import FrameResult, RunStats
from lightflow.app.sinks.background import BackgroundSink
from lightflow.app.status import CAUSE_PREFIX

#: end of stream marker passed down the queues (never dropped)
_END = object()
#: how often camera.stats() is read on the capture thread
CAMERA_STATS_INTERVAL_S = 0.5
#: smoothing of the fps estimate (weight of the newest sample)
EMA_ALPHA = 0.1
#: the camera's data rate is the bytes delivered over the last RATE_WINDOW_S seconds ...
RATE_WINDOW_S = 1.0
#: ... and is not reported before the frames it counts span this long: a replay's
#: read-ahead hands its first frames over microseconds apart, which is no data rate
RATE_MIN_SPAN_S = 0.25


class RateMeter:
    """The data rate of a stream, in MiB/s, over a sliding window of arrival times.

    An average of per-frame rates (bytes over the gap since the previous frame)
    is dominated by the shortest gaps: a burst of frames handed over at once
    reads as thousands of MiB/s.  Bytes over the window's span are not.

    Parameters
    ----------
    window_s : float
        Length of the window in seconds.
    min_span_s : float
        Shortest span of arrivals that gives a rate; before that :meth:`add` returns 0.
    """

    def __init__(self, window_s: float = RATE_WINDOW_S, min_span_s: float = RATE_MIN_SPAN_S):
        self.window_s = window_s
        self.min_span_s = min_span_s
        self._arrivals: collections.deque[tuple[float, int]] = collections.deque()
        self._bytes = 0  # bytes in the window, the oldest arrival included

    def add(self, t: float, nbytes: int) -> float:
        """Count ``nbytes`` arriving at time ``t`` (seconds) and return the rate in MiB/s.

        Returns
        -------
        float
            Bytes that arrived after the window's oldest arrival, over the time
            since it, in MiB/s; 0 while the arrivals span less than ``min_span_s``.
        """
        self._arrivals.append((t, nbytes))
        self._bytes += nbytes
        # keep one arrival at or before the window's start: it opens the span
        while len(self._arrivals) > 2 and self._arrivals[1][0] <= t - self.window_s:
            self._bytes -= self._arrivals.popleft()[1]
        t_first, n_first = self._arrivals[0]
        span = t - t_first
        if span < self.min_span_s:
            return 0.0
        return (self._bytes - n_first) / 2**20 / span


class DropOldestQueue:
    """A bounded FIFO whose ``put`` drops the oldest item when full (or blocks when lossless).

    Parameters
    ----------
    maxsize : int
        Capacity (at least 1).
    lossless : bool
        Block ``put`` while full instead of dropping.
    name : str
        Shown in the statistics (``dropped_<name>``).
    """

    def __init__(self, maxsize: int, lossless: bool = False, name: str = "queue"):
        self.maxsize = max(1, int(maxsize))
        self.lossless = lossless
        self.name = name
        self.dropped = 0
        self._items: collections.deque = collections.deque()
        self._cond = threading.Condition()
        self._aborted = False

    def put(self, item: Any) -> bool:
        """Add an item; return False when the queue was aborted (item discarded)."""
        with self._cond:
            while self.lossless and len(self._items) >= self.maxsize and not self._aborted:
                self._cond.wait()
            if self._aborted:
                return False
            if len(self._items) >= self.maxsize:
                self._items.popleft()
                self.dropped += 1
            self._items.append(item)
            self._cond.notify_all()
            return True

    def put_end(self) -> None:
        """Mark the end of the stream; never blocks, never dropped."""
        with self._cond:
            self._items.append(_END)
            self._cond.notify_all()

    def get(self) -> Any:
        """Next item, or the end marker once the stream ended or the queue was aborted."""
        with self._cond:
            while not self._items and not self._aborted:
                self._cond.wait()
            if self._aborted:
                return _END
            item = self._items.popleft()
            self._cond.notify_all()
            return item

    def abort(self) -> None:
        """Wake everyone: producers discard, consumers see the end (the other side is gone)."""
        with self._cond:
            self._aborted = True
            self._items.clear()
            self._cond.notify_all()

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)


class Runner:
    """Run a camera through a depth pipeline into sinks on three worker threads.

    Parameters
    ----------
    camera : Camera
        An *opened* camera (the caller opens and closes it, e.g. to set its
        size and exposure first).  Only the capture thread iterates it.
    pipeline : object
        Anything with ``process(frame) -> FrameResult`` (a
        :class:`~lightflow.app.core.pipeline.DepthPipeline`).  Only the processing
        thread calls it.
    sinks : iterable of Sink
        Written in order, one ``write(result, stats)`` per result; closed
        exactly once when the run ends, whatever happened.
    queue_size : int
        Capacity of each of the two queues.
    on_stats : callable, optional
        ``on_stats(stats)`` on the sink thread after every result (e.g. a status line).
    lossless : bool
        Block instead of dropping when a queue is full (offline replay).
    on_result : callable, optional
        ``on_result(result)`` on the sink thread before the sinks.
    recorder : RecordingWriter, optional
        Gets *every* frame the camera delivers, on the capture thread, before
        any queue can drop it (so a recording is complete even when the
        pipeline falls behind); closed by the capture thread at the end.
    max_frames : int, optional
        End the run after this many frames from the camera.
    count_gaps : bool
        Count gaps in ``frame.index`` as frames the camera lost (not for a
        replay, whose gaps are bad frames it lists itself).
    on_warning : callable, optional
        ``on_warning(text)`` once when the recorder falls behind the camera
        (its queue half full), with the rate needed and the rate achieved.
    background_sinks : bool
        Give every sink its own writer thread behind a bounded queue
        (:class:`~lightflow.app.sinks.background.BackgroundSink`), so the sink
        thread never waits on a disk.  A sink passed already wrapped keeps its
        own setting; any other one *blocks* when full, so no result is skipped
        (drops happen, counted, only in a live run's results queue).

    Examples
    --------
    Blocking::

        with camera:
            stats = Runner(camera, pipeline, sinks).run(stop)

    With the main thread busy (pyglet)::

        runner.start(stop)
        windows.run(stop)     # returns when stop is set (also set when the run ends)
        stats = runner.join()
    """

    def __init__(
        self,
        camera,
        pipeline,
        sinks: Iterable,
        queue_size: int = 4,
        on_stats: Callable[[RunStats], None] | None = None,
        lossless: bool = False,
        on_result: Callable[[FrameResult], None] | None = None,
        recorder=None,
        max_frames: int | None = None,
        count_gaps: bool = True,
        on_warning: Callable[[str], None] | None = None,
        background_sinks: bool = True,
    ):
        self.camera = camera
        self.pipeline = pipeline
        self.sinks = [
            s if not background_sinks or isinstance(s, BackgroundSink) else BackgroundSink(s)
            for s in sinks
        ]
        self.on_stats = on_stats
        self.on_result = on_result
        self.lossless = lossless
        self.recorder = recorder
        self.max_frames = max_frames
        self.count_gaps = count_gaps
        self.on_warning = on_warning
        self._warned: set[str] = set()
        self._recorder_warned = False
        self.frames_q = DropOldestQueue(queue_size, lossless, "frames")
        self.results_q = DropOldestQueue(queue_size, lossless, "results")
        self._stats = RunStats()
        self._lock = threading.Lock()
        self._error: BaseException | None = None
        self._threads: list[threading.Thread] = []
        self._stop: threading.Event | None = None
        self._ended = threading.Event()
        self._started = False
        self.sinks_closed = False
        #: True when the run ended because ``stop`` was set (Ctrl-C, window closed)
        self.stopped = False
        #: what the user closed, when a sink's window was closed (the run then stopped)
        self.closed_output: str | None = None
        self._closed_sinks: list = []
        self.interrupted = False

    # ------------------------------------------------------------------ public

    @property
    def stats(self) -> RunStats:
        """A consistent copy of the live statistics."""
        with self._lock:
            return copy.deepcopy(self._stats)

    @property
    def error(self) -> BaseException | None:
        return self._error

    def start(self, stop: threading.Event) -> None:
        """Start the worker threads; ``stop`` ends the run early and is set when it ends."""
        if self._started:
            raise RuntimeError("Runner.start() called twice")
        self._started = True
        self._stop = stop
        # everything allocated so far (modules, tables, kernels) lives as long as the
        # process: out of the collector's way, a full collection during the run costs
        # a fraction of a millisecond instead of tens
        gc.freeze()
        self._t0 = time.perf_counter()
        targets = [
            ("lightflow-capture", self._capture),
            ("lightflow-process", self._process),
            ("lightflow-sink", self._sink),
            ("lightflow-stop", self._watch_stop),
        ]
        self._threads = [threading.Thread(target=f, name=n, daemon=True) for n, f in targets]
        for t in self._threads:
            t.start()

    def join(self) -> RunStats:
        """Wait for the workers; re-raise the first worker exception; return the final stats."""
        for t in self._threads:
            t.join()
        if self._error is not None:
            raise self._error
        return self.stats

    def run(self, stop: threading.Event | None = None) -> RunStats:
        """Start, wait until the camera is exhausted or ``stop`` is set, and join.

        Ctrl-C while waiting stops the run cleanly (sinks drained and closed)
        and sets :attr:`interrupted` instead of raising.
        """
        stop = stop if stop is not None else threading.Event()
        self.start(stop)
        try:
            # Thread.join is interruptible by Ctrl-C on the main thread
            for t in self._threads:
                t.join()
        except KeyboardInterrupt:
            self.interrupted = True
            stop.set()
        return self.join()

    # ------------------------------------------------------------------ workers

    def _fail(self, exc: BaseException) -> None:
        with self._lock:
            if self._error is None:
                self._error = exc

    def _watch_stop(self) -> None:
        assert self._stop is not None
        self._stop.wait()
        if not self._ended.is_set():
            self.stopped = True
        self.camera.stop()  # frames() ends soon; the capture thread then ends the stream

    def _capture(self) -> None:
        q = self.frames_q
        last_index: int | None = None
        meter = RateMeter()
        next_stats = 0.0
        count = 0
        frames = None
        try:
            if self.max_frames is not None and self.max_frames <= 0:
                return
            frames = self.camera.frames()
            for frame in frames:
                now = time.perf_counter()
                nbytes = frame.image.nbytes
                with self._lock:
                    s = self._stats
                    s.frames_in += 1
                    gap = last_index is not None and frame.index > last_index + 1
                    if gap and self.count_gaps:
                        s.camera_lost += frame.index - last_index - 1
                    s.mib_per_s = meter.add(now, nbytes)
                last_index = frame.index
                if now >= next_stats:
                    next_stats = now + CAMERA_STATS_INTERVAL_S
                    self._update_camera_stats()
                if self.recorder is not None:
                    self.recorder.write(frame)
                    self._update_recorder_stats()
                if not q.put((frame, now)):
                    break  # downstream is gone
                self._update_drops()
                if self._stop.is_set():
                    break
                if self.max_frames is not None and count + 1 >= self.max_frames:
                    break
                count += 1
            if frames is not None and hasattr(frames, "close"):
                frames.close()  # on this thread: a live driver stops streaming here
        except BaseException as exc:  # noqa: BLE001 - stored, re-raised by join()
            self._fail(exc)
        finally:
            self._update_camera_stats()
            q.put_end()  # the downstream threads drain what they have and close the sinks
            if self.recorder is not None:
                try:
                    self.recorder.close()  # writes what is queued, then recording.json
                except BaseException as exc:  # noqa: BLE001 - stored, re-raised by join()
                    self._fail(exc)
                self._update_recorder_stats()

    def _update_camera_stats(self) -> None:
        try:
            cam_stats = self.camera.stats()
        except Exception:  # noqa: BLE001 - statistics are best effort, never end a run
            return
        with self._lock:
            for k, v in cam_stats.items():
                self._stats.extra[f"camera_{k}"] = float(v)

    def _update_recorder_stats(self) -> None:
        rs = self.recorder.stats()
        with self._lock:
            self._stats.extra["recorder_written"] = float(rs["written"])
            self._stats.extra["recorder_dropped"] = float(rs["dropped"])
            self._stats.extra["recorder_queued"] = float(rs["queued"])
            needed = self._stats.mib_per_s
        capacity = rs.get("capacity", 0)
        if capacity and rs["queued"] > capacity / 2 and not self._recorder_warned:
            self._recorder_warned = True
            elapsed = time.perf_counter() - self._t0
            achieved = rs["mib_written"] / elapsed if elapsed > 0 else 0.0
            if self.on_warning is not None:
                self.on_warning(
                    f"the recorder is falling behind: the camera delivers {needed:.0f} MiB/s, "
                    f"the disk took {achieved:.0f} MiB/s so far ({rs['queued']} frames waiting)"
                )

    def _warn_once(self, text: str) -> None:
        """Pass a frame's warning on the first time it is seen (the same text is not repeated)."""
        key = text.split(":")[0]
        if key in self._warned:
            return
        self._warned.add(key)
        if self.on_warning is not None:
            self.on_warning(text)

    def _update_drops(self) -> None:
        with self._lock:
            s = self._stats
            s.extra["dropped_frames_queue"] = float(self.frames_q.dropped)
            s.extra["dropped_results_queue"] = float(self.results_q.dropped)
            sink_drops = sum(getattr(k, "dropped", 0) for k in self.sinks
                             if isinstance(k, BackgroundSink))  # fmt: skip
            if sink_drops:
                s.extra["dropped_sinks"] = float(sink_drops)
            s.dropped = self.frames_q.dropped + self.results_q.dropped + sink_drops

    def _process(self) -> None:
        try:
            # the first frame's lines are compared with the next frame's (see
            # DepthPipeline.process): it waits for that frame
            item = self.frames_q.get()
            following = None if item is _END else self.frames_q.get()
            while item is not _END:
                frame, t_capture = item
                ahead = None if following is None or following is _END else following[0]
                result = self.pipeline.process(frame, ahead)
                total = result.timings_ms.get("total")
                if total is not None:
                    with self._lock:
                        e = self._stats.extra
                        old = e.get("process_ms")
                        e["process_ms"] = total if old is None else _ema(old, total)
                if not self.results_q.put((result, t_capture)):
                    break
                self._update_drops()
                item = self.frames_q.get() if following is None else following
                following = None
        except BaseException as exc:  # noqa: BLE001 - stored, re-raised by join()
            self._fail(exc)
            self.frames_q.abort()  # unblock the capture thread
            self._stop.set()
        finally:
            self.results_q.put_end()

    def _sink(self) -> None:
        last_done: float | None = None
        try:
            while True:
                item = self.results_q.get()
                if item is _END:
                    break
                result, t_capture = item
                if self.on_result is not None:
                    self.on_result(result)
                now = time.perf_counter()
                with self._lock:
                    s = self._stats
                    s.frames_done += 1
                    lat = (now - t_capture) * 1e3
                    s.latency_ms = lat if s.frames_done == 1 else _ema(s.latency_ms, lat)
                    if last_done is not None and now > last_done:
                        fps = 1.0 / (now - last_done)
                        s.fps = fps if s.fps == 0 else _ema(s.fps, fps)
                    s.extra["coverage"] = float(result.coverage)
                    _count_causes(s.extra, result)
                    snapshot = copy.deepcopy(s)
                last_done = now
                for text in result.warnings:
                    self._warn_once(text)
                for sink in self.sinks:
                    if sink in self._closed_sinks:
                        continue
                    try:
                        sink.write(result, snapshot)
                    except OutputClosed as exc:
                        # the user closed its window: stop as after Ctrl-C; the frames
                        # already queued still reach the other outputs
                        self._closed_sinks.append(sink)
                        if self.closed_output is None:
                            self.closed_output = str(exc)
                        self._stop.set()
                if self.on_stats is not None:
                    self.on_stats(snapshot)
        except BaseException as exc:  # noqa: BLE001 - stored, re-raised by join()
            self._fail(exc)
            # nobody consumes any more: let the producers end at once
            self.results_q.abort()
            self.frames_q.abort()
            self._stop.set()
        finally:
            self._close_sinks()
            self._update_drops()
            self._ended.set()
            self._stop.set()  # ends the stop watcher and a pyglet loop waiting on it

    def _close_sinks(self) -> None:
        if self.sinks_closed:
            return
        self.sinks_closed = True
        for sink in self.sinks:
            try:
                sink.close()
            except OutputClosed as exc:  # closed during the last frames: not an error
                if self.closed_output is None:
                    self.closed_output = str(exc)
            except BaseException as exc:  # noqa: BLE001 - every sink still gets closed
                self._fail(exc)


def _count_causes(extra: dict, result) -> None:
    """Add one frame's pixels per cause (and its colour-leak state) to the run's stats."""
    if result.cause_counts is None:
        return
    from .core.causes import CAUSE_NAMES

    for name, n in zip(CAUSE_NAMES, result.cause_counts, strict=True):
        key = CAUSE_PREFIX + name
        extra[key] = extra.get(key, 0.0) + float(n)
    if not result.leak_known:
        extra["leak_unknown_frames"] = extra.get("leak_unknown_frames", 0.0) + 1.0


def _ema(old: float, new: float) -> float:
    return (1 - EMA_ALPHA) * old + EMA_ALPHA * new
