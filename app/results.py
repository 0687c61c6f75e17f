"""What the depth pipeline produces per frame, as consumed by every sink."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lightflow.drivers.base import Frame


@dataclass
class BandSet:
    """Detected bands of one pattern (one colour channel) in one frame.

    Attributes
    ----------
    channel : str
        ``red``, ``green`` or ``blue``.
    rows : numpy.ndarray
        ``(n,)`` float32 image row of each band.
    starts, ends : numpy.ndarray
        ``(n,)`` float32 sub-pixel column of the band's two half-height edges.
    valid : numpy.ndarray
        ``(n,)`` bool: the band passed every check and contributes a flow.
    """

    channel: str
    rows: np.ndarray
    starts: np.ndarray
    ends: np.ndarray
    valid: np.ndarray


@dataclass
class FrameResult:
    """Per-frame output of :class:`lightflow.app.pipeline.DepthPipeline`.

    Maps named ``*_grid`` are on the analysis grid: every ``stride``-th row
    and column of the camera image; ``depth`` is at full camera resolution.

    Attributes
    ----------
    frame : Frame
        The input frame (its image is the RGB camera image).
    depth : numpy.ndarray
        ``(H, W)`` float32 depth z in metres (camera frame), NaN without estimate.
    flows_grid : list of numpy.ndarray
        Per pattern, the light flow in projector pixels, NaN where invalid.
    log_ratio_grid : numpy.ndarray
        ``log(flow_1 / flow_2)`` after smoothing, NaN where invalid.
    bands : list of BandSet
        Per pattern, the detected bands (for display).
    stride : int
        Grid stride of the ``*_grid`` maps.
    timings_ms : dict
        Time spent in each pipeline stage for this frame.
    coverage : float
        Fraction of the camera pixels that got a depth.
    """

    frame: Frame
    depth: np.ndarray
    flows_grid: list[np.ndarray]
    log_ratio_grid: np.ndarray
    bands: list[BandSet]
    stride: int
    timings_ms: dict[str, float] = field(default_factory=dict)
    coverage: float = 0.0


@dataclass
class RunStats:
    """Live statistics of a capture or replay run (shown in the terminal and in Rerun)."""

    frames_in: int = 0
    frames_done: int = 0
    dropped: int = 0
    camera_lost: int = 0
    fps: float = 0.0
    latency_ms: float = 0.0
    mib_per_s: float = 0.0
    extra: dict[str, float] = field(default_factory=dict)
