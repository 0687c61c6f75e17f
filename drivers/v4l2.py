"""USB webcams and other Video4Linux2 cameras (``v4l2:/dev/videoN``).

Built on the thin ioctl layer in :mod:`lightflow.drivers.v4l2_ioctl`; pass
``io=`` to swap the operating-system I/O (tests do, as no V4L2 device can exist
on their machine).

Buffer lifetime: the driver streams into a pool of mmap buffers that holds
about ``buffer_s`` seconds of frames (at least 4, capped by ``max_buffer_mib``;
the kernel may grant fewer, uvcvideo at most 32).  One acquisition thread per
camera owns the stream: it only dequeues a buffer (VIDIOC_DQBUF), copies its
bytes out and queues it again (VIDIOC_QBUF), so the pool never starves however
slow the consumer is, and a yielded image is never overwritten.  The copies
wait in a memory-capped queue (``max_pending_mib``) for
:meth:`V4L2Camera.frames`, which converts them on the consumer's thread.
Nothing is lost silently; :meth:`V4L2Camera.stats` counts, by cause, frames
dropped from that queue when the consumer fell behind by more than the cap
(``dropped_in_driver``, the oldest go first), frames still queued when
:meth:`V4L2Camera.stop` ended the stream (``discarded_at_stop``), gaps in the
kernel's sequence numbers (``missing_frames``), error-flagged buffers
(``failures``) and frames that could not be decoded (``bad_buffers``).
"""

from __future__ import annotations

import errno
import glob
import math
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from fractions import Fraction

import cv2
import numpy as np

from lightflow.app.core.errors import DeviceLostError, DriverError
from lightflow.drivers import v4l2_ioctl as v4l2
from lightflow.drivers.base import Camera, Frame, FrameHandoff

#: Supported pixel formats, preferred first: RGB3 needs no conversion, YUYV is
#: uncompressed (MJPG's block artefacts blur the lines the depth comes from).
PREFERRED_FORMATS = ("RGB3", "YUYV", "MJPG")
MIN_BUFFERS = 4
#: seconds of frames the mmap buffer pool holds by default
BUFFER_SECONDS = 1.0
#: memory caps (MiB) of the buffer pool and of the queue of copied-out frames
MAX_BUFFER_MIB = 512
MAX_PENDING_MIB = 1024
#: frame rate assumed when the device does not report one
DEFAULT_FPS = 30.0
# the acquisition thread's longest wait for a buffer: how soon it notices stop()
WAIT_S = 0.1
# Errors meaning the device node went away (unplugged, driver unbound).
_GONE = {errno.ENODEV, errno.ENXIO, errno.EIO, errno.ESHUTDOWN}

#: the counters of :meth:`V4L2Camera.stats`
#: (``dropped_in_driver`` and ``discarded_at_stop`` are counted by the frame hand-off)
_COUNTS = ("delivered", "failures", "missing_frames", "bad_buffers")

PERMISSION_HINT = (
    "add your user to the 'video' group (sudo usermod -aG video $USER, then log in again) "
    "or install lightflow's udev rules (see udev/README.md)"
)


def convert_frame(data: bytes | memoryview, code: str, width: int, height: int,
                  bytesperline: int = 0) -> np.ndarray:
    """Convert one V4L2 frame to an ``(height, width, 3)`` RGB ``uint8`` array.

    Parameters
    ----------
    data : bytes-like
        The frame as dequeued (``bytesused`` bytes).
    code : str
        Pixel format: ``YUYV`` (4:2:2, BT.601), ``MJPG`` (JPEG per frame) or
        ``RGB3`` (packed RGB).
    width, height : int
        Negotiated image size.
    bytesperline : int
        Row stride in bytes (0: tightly packed).

    Returns
    -------
    numpy.ndarray
        A new array the caller owns.
    """
    if code == "MJPG":
        bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        if bgr is None or bgr.shape[:2] != (height, width):
            got = "undecodable" if bgr is None else f"{bgr.shape[1]}x{bgr.shape[0]}"
            raise DriverError(f"MJPG frame is {got}, expected {width}x{height}")
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    bpp = {"YUYV": 2, "RGB3": 3}.get(code)
    if bpp is None:
        raise DriverError(f"pixel format {code} is not supported")
    stride = bytesperline or width * bpp
    if len(data) < stride * (height - 1) + width * bpp:
        raise DriverError(
            f"{code} frame of {width}x{height} needs {stride * height} bytes, got {len(data)}"
        )
    raw = np.frombuffer(data, np.uint8, count=min(len(data), stride * height))
    if raw.size < stride * height:
        raw = np.concatenate([raw, np.zeros(stride * height - raw.size, np.uint8)])
    rows = raw.reshape(height, stride)[:, : width * bpp]
    if code == "RGB3":
        return rows.reshape(height, width, 3).copy()
    return cv2.cvtColor(np.ascontiguousarray(rows).reshape(height, width, 2),
                        cv2.COLOR_YUV2RGB_YUYV)


@dataclass(frozen=True)
class V4L2DeviceInfo:
    """A video capture node found by :func:`list_v4l2_devices`."""

    path: str
    card: str = ""
    driver: str = ""
    bus_info: str = ""
    #: fourcc -> frame sizes (largest of a stepwise range)
    formats: dict[str, list[tuple[int, int]]] | None = None
    #: why the node could not be queried (permission denied, not a capture node, ...)
    problem: str = ""


def list_v4l2_devices(io: v4l2.DeviceIO | None = None,
                      paths: list[str] | None = None) -> list[V4L2DeviceInfo]:
    """Scan ``/dev/video*`` and describe every node (capture formats and sizes).

    Nodes that cannot be opened are listed with ``problem`` set (e.g. how to
    fix a permission problem); nodes without video capture (metadata nodes of
    UVC cameras) are skipped.
    """
    if paths is None:
        paths = sorted(glob.glob("/dev/video*"), key=lambda p: (len(p), p))
    found = []
    for path in paths:
        try:
            dev = v4l2.V4L2Device(path, io)
        except PermissionError:
            found.append(V4L2DeviceInfo(path, problem=f"permission denied; {PERMISSION_HINT}"))
            continue
        except OSError as exc:
            found.append(V4L2DeviceInfo(path, problem=exc.strerror or str(exc)))
            continue
        try:
            driver, card, bus, caps = dev.querycap()
            if not caps & v4l2.CAP_VIDEO_CAPTURE:
                continue
            formats = {code: dev.enum_framesizes(code) for code, _ in dev.enum_formats()}
            found.append(V4L2DeviceInfo(path, card, driver, bus, formats))
        except OSError as exc:
            found.append(V4L2DeviceInfo(path, problem=exc.strerror or str(exc)))
        finally:
            dev.close()
    return found


class V4L2Camera(Camera):
    """A V4L2 video capture device, streaming through mmap buffers.

    Parameters
    ----------
    path : str
        Device node, e.g. ``/dev/video0``.
    pixel_format : str, optional
        ``RGB3``, ``YUYV`` or ``MJPG``; by default the first of
        :data:`PREFERRED_FORMATS` the device offers.
    n_buffers : int, optional
        mmap buffers to request (at least 4).  By default the pool holds
        ``buffer_s`` seconds of frames at the device's frame rate.
    io : DeviceIO, optional
        The operating-system I/O (default: the real one).
    buffer_s : float
        Seconds of frames in the default buffer pool.
    max_buffer_mib, max_pending_mib : float
        Memory caps of the buffer pool and of the queue of copied-out frames
        waiting for the consumer.

    Only one thread iterates :meth:`frames`; :meth:`stop` may be called from any thread.
    """

    def __init__(self, path: str, pixel_format: str | None = None,
                 n_buffers: int | None = None, io: v4l2.DeviceIO | None = None,
                 buffer_s: float = BUFFER_SECONDS, max_buffer_mib: float = MAX_BUFFER_MIB,
                 max_pending_mib: float = MAX_PENDING_MIB) -> None:
        self.path = path
        self.uri = f"v4l2:{path}"
        self.requested_format = pixel_format
        self.n_buffers = None if n_buffers is None else max(MIN_BUFFERS, int(n_buffers))
        self.buffer_s = float(buffer_s)
        self.max_buffer_mib = float(max_buffer_mib)
        self.max_pending_mib = float(max_pending_mib)
        #: mmap buffers the kernel granted for the current (or last) stream
        self.pool_size = 0
        self.pixel_format = ""
        self.card = ""
        self._io = io
        self._dev: v4l2.V4L2Device | None = None
        self._pix: v4l2.PixFormat | None = None
        self._maps: list = []
        self._stop = threading.Event()
        self._idle = threading.Event()
        self._idle.set()
        self._streaming_thread: int | None = None
        self._handoff = FrameHandoff(self.max_pending_mib * 2**20)
        self._acq_thread: threading.Thread | None = None
        self._exposure_s = float("nan")
        self._counts = dict.fromkeys(_COUNTS, 0)

    # -- opening and closing -------------------------------------------------

    def _fail(self, what: str, exc: OSError) -> DriverError:
        if exc.errno in _GONE:
            return DeviceLostError(f"{self.uri}: device lost ({what}: {exc.strerror})")
        if exc.errno == errno.ENOTTY:
            return DriverError(f"{self.uri}: not a V4L2 device ({what}: {exc.strerror})")
        return DriverError(f"{self.uri}: {what} failed ({exc.strerror or exc})")

    def open(self) -> None:
        """Open the node, check it captures video, choose the format, switch auto controls off."""
        if self._dev is not None:
            return
        try:
            self._dev = v4l2.V4L2Device(self.path, self._io)
        except PermissionError:
            raise DriverError(f"{self.uri}: permission denied; {PERMISSION_HINT}") from None
        except FileNotFoundError:
            raise DriverError(f"{self.uri}: no such device (is the camera plugged in?)") from None
        except OSError as exc:
            raise self._fail("open", exc) from None
        try:
            self._configure()
        except BaseException:
            self.close()
            raise

    def _configure(self) -> None:
        dev = self._dev
        try:
            _driver, self.card, _bus, caps = dev.querycap()
            offered = [code for code, _ in dev.enum_formats()]
        except OSError as exc:
            raise self._fail("query", exc) from None
        if not caps & v4l2.CAP_VIDEO_CAPTURE or not caps & v4l2.CAP_STREAMING:
            raise DriverError(f"{self.uri}: not a streaming video capture device")
        if self.requested_format:
            if self.requested_format not in PREFERRED_FORMATS:
                raise DriverError(f"{self.uri}: pixel format {self.requested_format} is not "
                                  f"supported (use one of {', '.join(PREFERRED_FORMATS)})")
            if self.requested_format not in offered:
                raise DriverError(f"{self.uri}: pixel format {self.requested_format} not offered "
                                  f"(device has {', '.join(offered)})")
            choice = self.requested_format
        else:
            usable = [f for f in PREFERRED_FORMATS if f in offered]
            if not usable:
                raise DriverError(f"{self.uri}: none of the device's pixel formats "
                                  f"({', '.join(offered)}) is supported")
            choice = usable[0]
        try:
            current = dev.g_fmt()
        except OSError as exc:
            raise self._fail("get format", exc) from None
        self._negotiate(choice, current.width, current.height)
        self.disable_auto()
        if self._query(v4l2.CID_EXPOSURE_ABSOLUTE) is not None:
            self._exposure_s = self.exposure_s

    def _negotiate(self, code: str, width: int, height: int) -> None:
        try:
            pix = self._dev.s_fmt(code, width, height)
        except OSError as exc:
            raise self._fail(f"set format {code} {width}x{height}", exc) from None
        got = v4l2.fourcc_str(pix.pixelformat)
        if got != code:
            raise DriverError(f"{self.uri}: asked for pixel format {code}, device gives {got}")
        self._pix = pix
        self.pixel_format = code

    def close(self) -> None:
        """Stop streaming, unmap buffers and close the node (safe to call twice)."""
        self.stop()
        acquisition = self._acq_thread
        if acquisition is not None and acquisition is not threading.current_thread():
            acquisition.join()  # it leaves within WAIT_S; then nothing touches the buffers
        if self._streaming_thread not in (None, threading.get_ident()):
            # frames() runs in another thread: let it join its acquisition thread
            # and free the buffers (it owns the stream)
            self._idle.wait(timeout=WAIT_S * 50)
        self._end_stream()
        if self._dev is not None:
            self._dev.close()
            self._dev = None

    # -- controls ------------------------------------------------------------

    def _set_ctrl(self, cid: int, value: int, name: str) -> int:
        """Set a control and return the value read back."""
        try:
            self._dev.s_ctrl(cid, value)
            return self._dev.g_ctrl(cid)
        except OSError as exc:
            raise self._fail(f"set {name}", exc) from None

    def disable_auto(self) -> None:
        """Switch auto exposure, auto gain and auto white balance off, and verify.

        Controls the device lacks are skipped.

        Raises
        ------
        DriverError
            If the device keeps one of them on.
        """
        for cid, off, name in (
            (v4l2.CID_EXPOSURE_AUTO, v4l2.EXPOSURE_MANUAL, "exposure_auto"),
            (v4l2.CID_AUTOGAIN, 0, "autogain"),
            (v4l2.CID_AUTO_WHITE_BALANCE, 0, "white_balance_automatic"),
        ):
            if self._query(cid) is None:
                continue
            if self._set_ctrl(cid, off, name) != off:
                raise DriverError(f"{self.uri}: device refuses to switch {name} to manual/off")

    def _query(self, cid: int) -> v4l2.QueryCtrl | None:
        try:
            return self._dev.queryctrl(cid)
        except OSError as exc:
            raise self._fail("query control", exc) from None

    @property
    def exposure_s(self) -> float:
        if self._query(v4l2.CID_EXPOSURE_ABSOLUTE) is None:
            return self._exposure_s
        try:
            return self._dev.g_ctrl(v4l2.CID_EXPOSURE_ABSOLUTE) * v4l2.EXPOSURE_UNIT_S
        except OSError as exc:
            raise self._fail("get exposure", exc) from None

    def set_exposure(self, seconds: float) -> float:
        """Manual exposure through ``exposure_absolute`` (100 µs units); returns the read-back.

        Raises
        ------
        DriverError
            If the device has no manual exposure or ``seconds`` is outside its range.
        """
        ctrl = self._query(v4l2.CID_EXPOSURE_ABSOLUTE)
        if ctrl is None:
            raise DriverError(f"{self.uri}: device has no exposure_absolute control")
        if self._query(v4l2.CID_EXPOSURE_AUTO) is not None:
            if self._set_ctrl(v4l2.CID_EXPOSURE_AUTO, v4l2.EXPOSURE_MANUAL, "exposure_auto") \
                    != v4l2.EXPOSURE_MANUAL:
                raise DriverError(f"{self.uri}: device refuses manual exposure")
        units = round(seconds / v4l2.EXPOSURE_UNIT_S)
        if ctrl.step > 1:
            units = ctrl.minimum + round((units - ctrl.minimum) / ctrl.step) * ctrl.step
        if not ctrl.minimum <= units <= ctrl.maximum:
            lo, hi = ctrl.minimum * v4l2.EXPOSURE_UNIT_S, ctrl.maximum * v4l2.EXPOSURE_UNIT_S
            raise DriverError(f"{self.uri}: exposure {seconds:g} s outside the device's range "
                              f"{lo:g}..{hi:g} s")
        self._exposure_s = self._set_ctrl(v4l2.CID_EXPOSURE_ABSOLUTE, units, "exposure_absolute") \
            * v4l2.EXPOSURE_UNIT_S
        return self._exposure_s

    def set_gain(self, gain: int) -> int:
        """Set the gain control (device units) and return the read-back value."""
        if self._query(v4l2.CID_GAIN) is None:
            raise DriverError(f"{self.uri}: device has no gain control")
        return self._set_ctrl(v4l2.CID_GAIN, int(gain), "gain")

    def set_frame_rate(self, fps: float) -> float:
        """Set the frame interval with S_PARM; returns the frame rate the device chose."""
        try:
            if not self._dev.g_parm().capability & v4l2.CAP_TIMEPERFRAME:
                raise DriverError(f"{self.uri}: device does not support setting the frame rate")
            period = Fraction(1 / fps).limit_denominator(100000)
            got = self._dev.s_parm(period.numerator, period.denominator).timeperframe
        except OSError as exc:
            raise self._fail("set frame rate", exc) from None
        if got.numerator == 0:
            raise DriverError(f"{self.uri}: device reported a frame interval of 0")
        return got.denominator / got.numerator

    @property
    def size(self) -> tuple[int, int]:
        return int(self._pix.width), int(self._pix.height)

    def set_size(self, width: int, height: int) -> None:
        """Negotiate ``width`` x ``height`` (S_FMT); DriverError naming both sizes if refused."""
        if (width, height) == self.size:
            return
        before = self.size
        self._negotiate(self.pixel_format, width, height)
        if self.size != (width, height):
            got = self.size
            self._negotiate(self.pixel_format, *before)
            raise DriverError(f"{self.uri}: asked for image size {width}x{height}, "
                              f"device gives {got[0]}x{got[1]}")

    # -- streaming -----------------------------------------------------------

    def stop(self) -> None:
        """Make a running :meth:`frames` end at once (thread-safe).

        Frames copied out but not yet yielded are discarded and counted
        (``discarded_at_stop``); the acquisition thread leaves within ``WAIT_S``.
        """
        self._stop.set()
        self._handoff.wake()

    def _frame_rate(self) -> float:
        """The device's frame rate from G_PARM, or DEFAULT_FPS if it does not say."""
        try:
            parm = self._dev.g_parm()
        except OSError:
            return DEFAULT_FPS
        tpf = parm.timeperframe
        if not parm.capability & v4l2.CAP_TIMEPERFRAME or not tpf.numerator or not tpf.denominator:
            return DEFAULT_FPS
        return tpf.denominator / tpf.numerator

    def _pool_request(self) -> int:
        """Buffers for ``buffer_s`` seconds of frames, at least 4, within ``max_buffer_mib``."""
        if self.n_buffers is not None:
            return self.n_buffers
        size = self._pix.sizeimage or self._pix.bytesperline * self._pix.height
        cap = int(self.max_buffer_mib * 2**20 // max(1, size))
        return max(MIN_BUFFERS, min(math.ceil(self._frame_rate() * self.buffer_s), cap))

    def _start_stream(self) -> None:
        dev = self._dev
        self._handoff = FrameHandoff(self.max_pending_mib * 2**20)
        try:
            count = dev.reqbufs(self._pool_request())
            if count < 2:
                raise DriverError(f"{self.uri}: device gave {count} buffers, need at least 2")
            self.pool_size = count
            for index in range(count):
                self._maps.append(dev.mmap(dev.querybuf(index)))
                dev.qbuf(index)
            dev.streamon()
        except OSError as exc:
            raise self._fail("start streaming", exc) from None

    def _end_stream(self) -> None:
        if not self._maps or self._dev is None:
            return
        try:
            self._dev.streamoff()
        except OSError:
            pass  # the device may be gone; closing the node frees the buffers anyway
        for m in self._maps:
            m.close()
        self._maps = []
        try:
            self._dev.reqbufs(0)
        except OSError:
            pass

    def frames(self) -> Iterator[Frame]:
        """Stream frames until :meth:`stop` or :meth:`close`.

        Buffers flagged with an error, and frames that cannot be decoded, are
        counted in :meth:`stats` and skipped.

        Raises
        ------
        DeviceLostError
            When the device disappears mid-stream (after the frames already
            copied out have been yielded).
        """
        if self._dev is None:
            raise DriverError(f"{self.uri}: camera is not open")
        self._stop.clear()
        self._idle.clear()
        self._streaming_thread = threading.get_ident()
        self._counts = dict.fromkeys(_COUNTS, 0)
        try:
            self._start_stream()
            self._acq_thread = threading.Thread(
                target=self._acquire, name=f"{self.uri} acquisition", daemon=True
            )
            self._acq_thread.start()
            yield from self._deliver()
        finally:
            self._stop.set()
            if self._acq_thread is not None:
                self._acq_thread.join()  # it leaves within WAIT_S
                self._acq_thread = None
            self._handoff.discard()  # copied out after stop(), or never asked for
            self._end_stream()
            self._streaming_thread = None
            self._idle.set()

    def _acquire(self) -> None:
        """The acquisition thread: dequeue, copy out, queue again; nothing else."""
        error = None
        try:
            dev = self._dev
            last_seq = None
            while not self._stop.is_set():
                if not dev.wait_readable(WAIT_S):
                    continue
                buf = dev.dqbuf()
                if buf is None:
                    continue
                try:
                    if last_seq is not None and buf.sequence > last_seq + 1:
                        self._counts["missing_frames"] += buf.sequence - last_seq - 1
                    last_seq = buf.sequence
                    if buf.flags & v4l2.BUF_FLAG_ERROR:
                        self._counts["failures"] += 1
                        continue
                    # bytes(): a copy that stays ours once the buffer is queued again
                    stamp = buf.timestamp.secs + buf.timestamp.usecs * 1e-6
                    item = (buf.sequence, bytes(self._maps[buf.index][: buf.bytesused]), stamp)
                finally:
                    dev.qbuf(buf.index)
                self._handoff.put(item)
        except OSError as exc:
            error = self._fail("dequeue", exc)
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer in _deliver
            error = exc
        finally:
            self._handoff.finish(error)

    def _deliver(self) -> Iterator[Frame]:
        """Convert and yield the copied-out frames, on the consumer's thread."""
        width, height = self.size
        stride = self._pix.bytesperline
        while True:
            item = self._handoff.get(self._stop)
            if item is None:
                return  # stopped, or the stream ended
            sequence, data, stamp = item
            try:
                image = convert_frame(data, self.pixel_format, width, height, stride)
            except DriverError:
                self._counts["bad_buffers"] += 1  # e.g. a truncated MJPG frame
                continue
            self._counts["delivered"] += 1
            exposure = self._exposure_s if not math.isnan(self._exposure_s) else 0.0
            yield Frame(index=sequence, timestamp=stamp, exposure_s=exposure, image=image)

    def stats(self) -> dict[str, float]:
        """Frame counts by cause, and ``buffers`` (the mmap pool the kernel granted).

        ``delivered``; ``failures`` (error-flagged buffers); ``missing_frames``
        (gaps in the kernel's sequence numbers); ``dropped_in_driver`` (the
        consumer fell behind by more than ``max_pending_mib``);
        ``discarded_at_stop``; ``bad_buffers`` (frames that could not be
        decoded).  Kept after streaming ends.
        """
        out = {k: float(v) for k, v in self._counts.items()}
        out["dropped_in_driver"] = float(self._handoff.dropped)
        out["discarded_at_stop"] = float(self._handoff.discarded)
        out["buffers"] = float(self.pool_size)
        return out
