"""Run a sink on its own thread behind a bounded queue, so the pipeline never waits on a disk.

::

    sink thread ──write()──▶ [bounded queue] ──▶ writer thread ──▶ wrapped sink

Results reach the wrapped sink in the order they were written (one writer
thread, FIFO), so every output keeps the recording's frame order.  When the
queue is full, a *blocking* wrapper makes the caller wait (a depth export
must not skip a frame); a non-blocking one drops the oldest queued result and
counts it in :attr:`BackgroundSink.dropped`, shown by :meth:`describe` and in
``stats.extra["dropped_sink_<name>"]`` - never silently.

The wrapped sink's first exception is re-raised, unchanged, from the next
``write`` or from ``close``; after it nothing more reaches that sink.
"""

from __future__ import annotations

import collections
import threading
from typing import Any

from lightflow.app.core.results import FrameResult, RunStats

#: results queued per sink by default (a 1600x1200 result is a few MiB)
DEFAULT_MAXSIZE = 4


class BackgroundSink:
    """Wrap ``sink`` so its ``write`` runs on a dedicated thread.

    Parameters
    ----------
    sink : Sink
        Anything with ``write(result, stats)`` and ``close()``.
    maxsize : int
        Results that may wait for the writer thread (at least 1).
    block : bool
        When the queue is full, wait (True: no result is ever skipped) or drop
        the oldest queued result and count it (False: a live view).
    name : str, optional
        Used in the thread name and the statistics key; default: the sink's class name.
    """

    def __init__(self, sink, maxsize: int = DEFAULT_MAXSIZE, block: bool = True,
                 name: str | None = None):  # fmt: skip
        self.sink = sink
        self.maxsize = max(1, int(maxsize))
        self.block = block
        self.name = name or type(sink).__name__
        #: results dropped because the sink could not keep up (only when not blocking)
        self.dropped = 0
        #: results the wrapped sink has written
        self.written = 0
        self._items: collections.deque = collections.deque()
        self._cond = threading.Condition()
        self._ending = False
        self._error: BaseException | None = None
        self._closed = False
        # started by the first write: a wrapper that never writes owns no thread
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ Sink

    def write(self, result: FrameResult, stats: RunStats) -> None:
        """Queue one result (wait or drop the oldest when full); raise the sink's error if any."""
        with self._cond:
            while self.block and len(self._items) >= self.maxsize and self._error is None:
                self._cond.wait()
            if self._error is not None:
                raise self._error
            if self._thread is None:
                self._thread = threading.Thread(
                    target=self._work, name=f"lightflow-sink-{self.name}", daemon=True
                )
                self._thread.start()
            if len(self._items) >= self.maxsize:
                self._items.popleft()
                self.dropped += 1
            if self.dropped:
                stats.extra[f"dropped_sink_{self.name}"] = float(self.dropped)
            self._items.append((result, stats))
            self._cond.notify_all()

    def close(self) -> None:
        """Write everything queued, close the wrapped sink, re-raise its first error."""
        if self._closed:
            return
        self._closed = True
        with self._cond:
            self._ending = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join()
        try:
            self.sink.close()
        except BaseException as exc:  # noqa: BLE001 - the earlier error wins
            if self._error is None:
                self._error = exc
        if self._error is not None:
            raise self._error

    def describe(self) -> str:
        """The wrapped sink's description, plus the results it skipped (if any)."""
        describe = getattr(self.sink, "describe", None)
        text = describe() if describe is not None else self.name
        if self.dropped:
            text += f"; {self.dropped} results SKIPPED (the output could not keep up)"
        return text

    def __getattr__(self, name: str) -> Any:
        # the wrapped sink's own attributes (e.g. a path) stay reachable
        if name == "sink":
            raise AttributeError(name)
        return getattr(self.sink, name)

    # ------------------------------------------------------------------ worker

    def _work(self) -> None:
        while True:
            with self._cond:
                while not self._items and not self._ending:
                    self._cond.wait()
                if not self._items:
                    return  # ending and drained
                result, stats = self._items.popleft()
                self._cond.notify_all()
            try:
                self.sink.write(result, stats)
                self.written += 1
            except BaseException as exc:  # noqa: BLE001 - re-raised by write()/close()
                with self._cond:
                    self._error = exc
                    self._items.clear()  # nothing more reaches a failed sink
                    self._cond.notify_all()
                return
