"""Sinks: the edges where results leave the pipeline (Rerun, files).

A sink has one method per frame, ``write(result)``, and ``close()``.  Sinks
run on the sink thread of :class:`lightflow.app.runner.Runner`; they may be
slow, the runner's bounded queue counts what they drop.
"""

from __future__ import annotations

from typing import Protocol

from lightflow.app.core.results import FrameResult, RunStats


class Sink(Protocol):
    def write(self, result: FrameResult, stats: RunStats) -> None:
        """Consume one processed frame."""

    def close(self) -> None:
        """Flush and release; nothing may be half-written afterwards."""
