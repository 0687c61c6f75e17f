"""What the depth pipeline produces per frame, as consumed by every sink."""

from __future__ import annotations

from dataclasses import InitVar, dataclass, field
from functools import cached_property

import cv2
import numpy as np

from .frame import Frame


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
    """Per-frame output of :class:`lightflow.app.core.pipeline.DepthPipeline`.

    Maps named ``*_grid`` are on the analysis grid: every ``stride``-th row
    and column of the camera image; ``depth`` is at full camera resolution.

    Attributes
    ----------
    frame : Frame
        The input frame (its image is the RGB camera image).
    depth : numpy.ndarray
        ``(H, W)`` float32 depth z in metres (camera frame), NaN without estimate.
        Either given, or upsampled from ``depth_grid`` on first use: the sinks that
        show or write it pay for it, on their own threads, not the pipeline.
    flows_grid : list of numpy.ndarray
        Per pattern, the light flow in projector pixels, NaN where invalid.
    log_ratio_grid : numpy.ndarray
        ``log(flow_1 / flow_2)`` after smoothing, NaN where invalid.
    bands : list of BandSet
        Per pattern, the detected bands (for display).
    stride : int
        Grid stride of the ``*_grid`` maps.
    timings_ms : dict
        Time spent in each pipeline stage for this frame (ms); ``total`` is the whole
        call, with ``next frame`` for a first frame processed after the next one
        (:meth:`DepthPipeline.process`'s ``following``).
    coverage : float
        Fraction of the analysis-grid pixels that got a depth ("depth on image").
    depth_std_grid : numpy.ndarray or None
        Predicted standard deviation of the depth (metres) on the analysis
        grid, NaN where there is no depth; :attr:`depth_std` is its full
        resolution map, upsampled on first use (only sinks that show or write
        it pay for it).
    causes_grid : numpy.ndarray or None
        uint8 :mod:`lightflow.app.core.causes` code per grid pixel: depth, or why not.
    cause_counts : numpy.ndarray or None
        Grid pixels per cause code (``len(CAUSES)`` counts).
    leak_known : bool
        Whether the colour leak between the patterns has been estimated yet
        (until then it is taken as 0).
    warnings : list of str
        Frame-level warnings (for example most pixels out of the model's range).
    intervals_grid : numpy.ndarray or None
        ``(2, h, w)``: per pattern, the measured line interval (camera px) on the
        grid, NaN without bands; with ``flows_grid`` it splits a flow's error into
        its band length and its interval (``lightflow eval --stages``).
    depth_grid : numpy.ndarray or None
        Depth on the analysis grid, when ``depth`` is not given.
    full_size : tuple of int or None
        ``(W, H)`` of the camera image, with ``depth_grid``.
    """

    frame: Frame
    depth_map: InitVar[np.ndarray | None]
    flows_grid: list[np.ndarray]
    log_ratio_grid: np.ndarray
    bands: list[BandSet]
    stride: int
    timings_ms: dict[str, float] = field(default_factory=dict)
    coverage: float = 0.0
    depth_std_grid: np.ndarray | None = None
    causes_grid: np.ndarray | None = None
    cause_counts: np.ndarray | None = None
    leak_known: bool = True
    warnings: list[str] = field(default_factory=list)
    intervals_grid: np.ndarray | None = None
    depth_grid: np.ndarray | None = None
    full_size: tuple[int, int] | None = None

    def __post_init__(self, depth_map: np.ndarray | None) -> None:
        if depth_map is None and (self.depth_grid is None or self.full_size is None):
            raise ValueError("FrameResult needs a depth map, or depth_grid and full_size")
        if depth_map is not None:
            self.__dict__["depth"] = depth_map  # what cached_property reads first

    @cached_property
    def depth(self) -> np.ndarray:
        """``(H, W)`` float32 depth in metres, NaN without estimate (see the class)."""
        return upsample_grid(self.depth_grid, self.stride, self.full_size)

    @cached_property
    def depth_std(self) -> np.ndarray | None:
        """``(H, W)`` float32 predicted standard deviation of ``depth`` (metres), or None.

        NaN exactly where ``depth`` is NaN (both are upsampled alike).
        """
        if self.depth_std_grid is None:
            return None
        h, w = self.depth.shape
        return upsample_grid(self.depth_std_grid, self.stride, (w, h))


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


#: share of the bilinear weight that must lie on valid samples for a full-resolution pixel
#: to get a value (see :func:`upsample_grid`)
KEEP_WEIGHT = 0.75


def upsample_grid(grid: np.ndarray, stride: int, size: tuple[int, int]) -> np.ndarray:
    """An analysis-grid map at full resolution, bilinear over the valid samples.

    A pixel gets a value where at least :data:`KEEP_WEIGHT` of its bilinear weight lies
    on finite samples (the value: their weighted mean), NaN elsewhere: a valid sample
    covers the part of its cell within a quarter cell of its centre, and all of it
    where its neighbours are valid too.

    Parameters
    ----------
    grid : numpy.ndarray
        ``(h, w)`` map with one sample at the centre of each ``stride`` x ``stride`` cell,
        or ``(h, w, c)`` with up to 4 channels (a colour image of it).
    stride : int
    size : tuple of int
        ``(width, height)`` of the full-resolution image.

    Returns
    -------
    numpy.ndarray
        ``(height, width)`` (or ``(height, width, c)``) map of ``grid``'s dtype.
    """
    if stride == 1 and grid.shape[:2] == (size[1], size[0]):
        return grid
    valid = np.isfinite(grid)
    if valid.all():
        return _bilinear(grid, stride, size)
    # NaN-aware: the valid samples interpolated alone, kept where most of the weight is
    # theirs.  Plain bilinear spreads a NaN over half of each neighbouring cell, so a hole
    # of one cell inside an object cost four cells' pixels; here it costs one and a half.
    # At an object's edge a cell is measured at its centre and the edge crosses it
    # anywhere: this threshold keeps the pixels within a quarter cell of the valid centre,
    # which on average adds as many pixels past the edge as it leaves short of it.
    # float64 maps stay float64 (any other dtype is interpolated in float32)
    work = np.float64 if grid.dtype == np.float64 else np.float32
    weight = _bilinear(valid.view(np.uint8).astype(work), stride, size)
    out = _bilinear(np.where(valid, grid, 0).astype(work), stride, size)
    # below the threshold the weight becomes 0, and x / 0 + (x / 0) * 0 is NaN, whereas
    # on finite values the sum adds nothing: whole-array arithmetic in place, several
    # times faster than writing NaN through a mask (each new 1600x1200 array costs
    # about 2 ms of page faults here)
    cv2.threshold(weight, KEEP_WEIGHT - 1e-4, 0, cv2.THRESH_TOZERO, dst=weight)
    with np.errstate(invalid="ignore", divide="ignore"):
        np.divide(out, weight, out=out)
        np.multiply(out, work(0), out=weight)
        np.add(out, weight, out=out)
    return out.astype(grid.dtype, copy=False)


def _bilinear(grid: np.ndarray, stride: int, size: tuple[int, int]) -> np.ndarray:
    gh, gw = grid.shape[:2]
    if (gw * stride, gh * stride) == tuple(size):
        # grid samples sit at cell centres, exactly where resize expects them
        return cv2.resize(grid, size, interpolation=cv2.INTER_LINEAR)
    # an image size that is no multiple of the stride: map pixel x to cell (x - off) / s
    off = 0.5 * (stride - 1)
    m = np.array([[1.0 / stride, 0.0, -off / stride], [0.0, 1.0 / stride, -off / stride]])
    return cv2.warpAffine(
        grid, m, size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REPLICATE,
    )  # fmt: skip
