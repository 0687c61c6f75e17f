"""GigE Vision and USB3 Vision cameras through Aravis (``aravis:<id or address>``).

Aravis is reached through PyGObject and imported lazily, so the rest of
lightflow works on machines without it.

Buffer lifetime: Aravis fills a pool of buffers in its own stream thread; the
pool holds about ``buffer_s`` seconds of frames (at least 8, capped by
``max_buffer_mib``).  One acquisition thread per camera owns the stream: it
only pops a buffer, copies the image bytes out and pushes the buffer straight
back, so the pool never starves however slow the consumer is.  The copies wait
in a memory-capped queue (``max_pending_mib``) for :meth:`AravisCamera.frames`,
which converts them on the consumer's thread.  A frame dropped from that queue
(the consumer fell behind by more than the cap) is counted in
``stats()["dropped_in_driver"]``, never silently.

Lost cameras: when no buffer arrives for ``lost_after_s`` seconds the driver
asks the control channel directly (an uncached register read); if that fails
or gets no answer within ``probe_timeout_s``,
or Aravis has signalled ``control-lost`` (heartbeat failure), ``frames()``
raises :class:`~lightflow.app.core.errors.DeviceLostError`.  Aravis alone would
take much longer: a GigE Vision transaction to a dead camera fails only after
5 tries of 500 ms (2.5 s), and its heartbeat thread retries for 5 s before it
signals ``control-lost``; so the loss is reported after about
``lost_after_s + probe_timeout_s`` (2 s by default), and the dead camera's
objects are freed by a daemon thread that never keeps the process alive.

Control held by another client: a GigE Vision camera obeys one controller at
a time, and a client that died without releasing it (kill -9) keeps the
camera until its heartbeat times out (GevHeartbeatTimeout, usually 3 s).
Aravis opens such a camera without control (``arv_gv_device_take_control``
failed, ``arv_gv_device_is_controller`` is false) and every write is refused.
:meth:`AravisCamera.open` then says so on one line and retries
``take_control`` until ``control_wait_s`` has passed, then raises a one-line
:class:`~lightflow.app.core.errors.DriverError`.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from lightflow.app.core.errors import DeviceLostError, DriverError
from lightflow.drivers.base import Camera, Frame, FrameHandoff
from lightflow.drivers.pixfmt import packed_row_bytes, packing, significant_bits, unpack

MIN_BUFFERS = 8
#: seconds of frames the Aravis buffer pool holds by default
BUFFER_SECONDS = 1.0
#: memory caps (MiB) of the buffer pool and of the queue of copied-out frames
MAX_BUFFER_MIB = 512
MAX_PENDING_MIB = 1024
_STAT_NAMES = {"n_completed_buffers": "completed"}
POP_TIMEOUT_S = 0.1
# Bootstrap register 0 (GigE Vision version / USB3 Vision GenCP version): every
# camera has it and reading it is a real round trip, never served from a cache.
_PROBE_REGISTER = 0x0000
# GigE Vision bootstrap register of the heartbeat timeout (GevHeartbeatTimeout, ms).
_HEARTBEAT_TIMEOUT_REGISTER = 0x0938
#: seconds to wait for a camera whose control channel another client holds
CONTROL_WAIT_S = 10.0
# A camera does not announce that its control channel became free: take_control
# is retried at this interval (a refusal comes back at once from a real camera).
CONTROL_RETRY_S = 0.5

#: Preferred pixel formats, best first: 8-bit colour (the rig's patterns are told
#: apart by colour channel), then deeper colour, then monochrome.
PREFERRED_FORMATS = (
    "RGB8", "RGB8Packed",
    "BayerRG8", "BayerGR8", "BayerGB8", "BayerBG8",
    "BayerRG16", "BayerGR16", "BayerGB16", "BayerBG16",
    "BayerRG12", "BayerGR12", "BayerGB12", "BayerBG12",
    "BayerRG10", "BayerGR10", "BayerGB10", "BayerBG10",
    "BayerRG12p", "BayerGR12p", "BayerGB12p", "BayerBG12p",
    "BayerRG12Packed", "BayerGR12Packed", "BayerGB12Packed", "BayerBG12Packed",
    "BayerRG10p", "BayerGR10p", "BayerGB10p", "BayerBG10p",
    "Mono8", "Mono16", "Mono12", "Mono12p", "Mono12Packed", "Mono10", "Mono10p",
    "Mono10Packed",
)  # fmt: skip

# GenICam names the colour of the first two pixels of the first row; OpenCV
# names those of the second row, hence the swap (BayerRG -> COLOR_BayerBG2RGB).
_BAYER_CODES = {
    "RG": cv2.COLOR_BayerBG2RGB,
    "GR": cv2.COLOR_BayerGB2RGB,
    "GB": cv2.COLOR_BayerGR2RGB,
    "BG": cv2.COLOR_BayerRG2RGB,
}


def supported_format(name: str) -> bool:
    """Whether :func:`convert_image` can convert the GenICam pixel format ``name``."""
    return _layout(name) is not None


def _layout(name: str) -> tuple[str, int] | None:
    """``(kind, bytes per sample)`` of a GenICam pixel format, None if unsupported.

    kind is ``mono``, ``rgb`` or a Bayer pattern (``RG``, ``GR``, ``GB``, ``BG``).
    10/12/16-bit formats are the unpacked ones (one 16-bit container per sample).
    """
    if name in ("RGB8", "RGB8Packed"):
        return "rgb", 1
    if packing(name) is not None:
        name = name.removesuffix("Packed").removesuffix("p")  # the unpacked twin
    for depth, size in (("8", 1), ("10", 2), ("12", 2), ("16", 2)):
        if name == f"Mono{depth}":
            return "mono", size
        for pattern in _BAYER_CODES:
            if name == f"Bayer{pattern}{depth}":
                return pattern, size
    return None


def convert_image(
    data: bytes | memoryview, pixel_format: str, width: int, height: int, row_padding: int = 0
) -> np.ndarray:
    """Convert raw camera image bytes to an ``(height, width, 3)`` RGB array.

    Parameters
    ----------
    data : bytes-like
        The image as the camera sent it.
    pixel_format : str
        GenICam pixel format name (``Mono8``, ``RGB8``, ``BayerRG8``, ``BayerGB12``, ...).
    width, height : int
        Image size in pixels.
    row_padding : int
        Bytes after each row (GigE Vision ``padding_x``).

    Returns
    -------
    numpy.ndarray
        A new, writable array: ``uint8`` for 8-bit formats, ``uint16`` (raw
        10/12/16-bit values, not rescaled; packed formats unpacked) otherwise.
        Mono is replicated to three channels; Bayer mosaics are demosaiced
        with OpenCV.
    """
    layout = _layout(pixel_format)
    if layout is None:
        raise DriverError(f"pixel format {pixel_format} is not supported")
    kind, size = layout
    channels = 3 if kind == "rgb" else 1
    packed = packing(pixel_format)
    if packed is not None:
        bits = significant_bits(pixel_format)
        row_bytes = packed_row_bytes(width, bits, packed)
        stride = row_bytes + row_padding
        if len(data) < stride * (height - 1) + row_bytes:
            raise DriverError(
                f"{pixel_format} image of {width}x{height} needs {stride * height} bytes, "
                f"got {len(data)}"
            )
        raw = np.frombuffer(data, dtype=np.uint8, count=min(len(data), stride * height))
        if raw.size < stride * height:
            raw = np.concatenate([raw, np.zeros(stride * height - raw.size, np.uint8)])
        mono = unpack(raw.reshape(height, stride)[:, :row_bytes], width, bits, packed)
        if kind == "mono":
            return cv2.cvtColor(mono, cv2.COLOR_GRAY2RGB)
        return cv2.cvtColor(mono, _BAYER_CODES[kind])
    dtype = np.uint8 if size == 1 else np.dtype("<u2")
    stride = width * channels * size + row_padding
    if len(data) < stride * (height - 1) + width * channels * size:
        raise DriverError(
            f"{pixel_format} image of {width}x{height} needs {stride * height} bytes, "
            f"got {len(data)}"
        )
    raw = np.frombuffer(data, dtype=np.uint8, count=min(len(data), stride * height))
    if raw.size < stride * height:  # last row without its padding
        raw = np.concatenate([raw, np.zeros(stride * height - raw.size, np.uint8)])
    rows = raw.reshape(height, stride)[:, : width * channels * size]
    samples = np.ascontiguousarray(rows).view(dtype).reshape(height, width, channels)
    if kind == "rgb":
        return samples.astype(samples.dtype.newbyteorder("="), copy=True)
    mono = samples[:, :, 0].astype(samples.dtype.newbyteorder("="))
    if kind == "mono":
        return cv2.cvtColor(mono, cv2.COLOR_GRAY2RGB)
    return cv2.cvtColor(mono, _BAYER_CODES[kind])


def _aravis():
    """Import Aravis through PyGObject, or raise DriverError saying how to install it."""
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis
    except (ImportError, ValueError) as exc:
        raise DriverError(
            f"Aravis is not available ({exc}); install the apt package gir1.2-aravis-0.8 "
            f"and `pip install lightflow[aravis]`"
        ) from None
    return Aravis


def _glib_error() -> type[BaseException]:
    from gi.repository import GLib

    return GLib.Error


@dataclass(frozen=True)
class AravisDeviceInfo:
    """One camera found by Aravis discovery."""

    id: str
    address: str
    vendor: str
    model: str
    serial: str
    protocol: str
    physical_id: str


def list_aravis_devices() -> list[AravisDeviceInfo]:
    """List the GigE Vision and USB3 Vision cameras Aravis can see.

    This runs Aravis discovery, which **broadcasts GigE Vision discovery
    packets on every network interface** and enumerates USB devices.  Tests
    run it only inside a private network namespace.

    Returns
    -------
    list of AravisDeviceInfo
        ``id`` (or ``address``) is what :class:`AravisCamera` accepts.
    """
    Aravis = _aravis()
    Aravis.update_device_list()
    found = []
    for i in range(Aravis.get_n_devices()):
        found.append(
            AravisDeviceInfo(
                id=Aravis.get_device_id(i) or "",
                address=Aravis.get_device_address(i) or "",
                vendor=Aravis.get_device_vendor(i) or "",
                model=Aravis.get_device_model(i) or "",
                serial=Aravis.get_device_serial_nbr(i) or "",
                protocol=Aravis.get_device_protocol(i) or "",
                physical_id=Aravis.get_device_physical_id(i) or "",
            )
        )
    return found


class AravisCamera(Camera):
    """A GenICam camera (GigE Vision or USB3 Vision) opened through Aravis.

    Parameters
    ----------
    device : str
        Aravis device id (``Basler-21234567``) or IP address (``192.168.1.20``).
    pixel_format : str, optional
        GenICam pixel format to use; by default the first of
        :data:`PREFERRED_FORMATS` the camera offers.
    n_buffers : int, optional
        Stream buffers in the pool (at least 8).  By default the pool holds
        ``buffer_s`` seconds of frames at the camera's frame rate.
    buffer_s : float
        Seconds of frames in the default buffer pool.
    max_buffer_mib, max_pending_mib : float
        Memory caps of the buffer pool and of the queue of copied-out frames
        waiting for the consumer.
    lost_after_s : float
        Seconds without a buffer after which the control channel is checked.
    probe_timeout_s : float
        How long that check waits for the camera to answer.
    control_wait_s : float
        How long :meth:`open` waits for a GigE camera whose control channel
        another client holds (a crashed program, until its heartbeat times
        out).  The last attempt may end up to 2.5 s later (one GigE Vision
        transaction with its retries).
    notify : callable, optional
        Receives the one-line notices (waiting for control, control taken);
        by default they are printed on stderr.

    Only one thread iterates :meth:`frames`; :meth:`stop` may be called from any thread.
    """

    def __init__(
        self,
        device: str,
        pixel_format: str | None = None,
        n_buffers: int | None = None,
        lost_after_s: float = 1.0,
        probe_timeout_s: float = 1.0,
        buffer_s: float = BUFFER_SECONDS,
        max_buffer_mib: float = MAX_BUFFER_MIB,
        max_pending_mib: float = MAX_PENDING_MIB,
        control_wait_s: float = CONTROL_WAIT_S,
        notify: Callable[[str], None] | None = None,
    ) -> None:
        self.device = device
        self.uri = f"aravis:{device}"
        self.requested_format = pixel_format
        self.n_buffers = None if n_buffers is None else max(MIN_BUFFERS, int(n_buffers))
        self.buffer_s = float(buffer_s)
        self.max_buffer_mib = float(max_buffer_mib)
        self.max_pending_mib = float(max_pending_mib)
        #: buffers in the pool of the current (or last) stream
        self.pool_size = 0
        self._handoff = FrameHandoff(self.max_pending_mib * 2**20)
        self._acq_thread: threading.Thread | None = None
        self._dropped_in_driver = 0
        self._discarded_at_stop = 0
        self.lost_after_s = float(lost_after_s)
        self.probe_timeout_s = float(probe_timeout_s)
        if not control_wait_s >= 0:
            raise DriverError(f"aravis:{device}: control wait must be >= 0 s, got {control_wait_s}")
        self.control_wait_s = float(control_wait_s)
        self.notify = notify if notify is not None else _print_notice
        self.pixel_format = ""
        self._cam: Any = None
        self._dev: Any = None
        self._stream: Any = None
        self._lost_handler: int | None = None
        self._control_lost = threading.Event()
        self._stop = threading.Event()
        self._idle = threading.Event()
        self._idle.set()
        self._streaming_thread: int | None = None
        self._exposure_s = 0.0
        self._last_stats: dict[str, float] = {}
        self._bad_buffers = 0
        self._delivered = 0
        self._gone = False
        self._probe: threading.Thread | None = None
        #: set once the Aravis objects are freed (at once, unless the camera was lost)
        self.released = threading.Event()
        self.released.set()

    # -- opening and closing -------------------------------------------------

    def open(self) -> None:
        """Connect to the camera, switch automatic controls off and choose the format."""
        if self._cam is not None:
            return
        Aravis = _aravis()
        try:
            self._cam = Aravis.Camera.new(self.device)
        except _glib_error() as exc:
            raise DriverError(f"{self.uri}: cannot open camera ({exc.message})") from None
        self._dev = self._cam.get_device()
        self._control_lost.clear()
        self._gone = False
        self._lost_handler = self._dev.connect("control-lost", self._on_control_lost)
        try:
            if self._cam.is_gv_device() and not self._dev.is_controller():
                self._wait_for_control()
            self._configure()
        except BaseException:
            self.close()
            raise

    def _wait_for_control(self) -> None:
        """Retry ``take_control`` until it succeeds or ``control_wait_s`` has passed.

        Called when Aravis opened a GigE camera without its control channel:
        another client holds it, typically one that died without releasing it,
        which the camera frees when that client's heartbeat times out.
        :meth:`stop` from another thread ends the wait early.

        Raises
        ------
        DriverError
            One line, when the deadline passes or the wait is stopped.
        DeviceLostError
            When the camera stops answering meanwhile.
        """
        dev = self._dev
        try:
            heartbeat = f"{dev.read_register(_HEARTBEAT_TIMEOUT_REGISTER) / 1e3:g} s"
        except _glib_error():
            heartbeat = "unknown"  # not every camera lets a non-controller read it
        self.notify(
            f"camera {self.uri} is controlled by another client (a crashed lightflow?); "
            f"waiting up to {self.control_wait_s:g} s for its heartbeat ({heartbeat}) "
            f"to time out ..."
        )
        self._stop.clear()
        start = time.monotonic()
        deadline = start + self.control_wait_s
        while True:
            try:
                if dev.take_control():
                    self.notify(f"camera {self.uri}: control taken after "
                                f"{time.monotonic() - start:.1f} s")
                    return
            except _glib_error():
                pass  # refused (access denied) or ignored (timeout): still held
            try:
                dev.read_register(_PROBE_REGISTER)  # refused, or gone?
            except _glib_error() as exc:
                self._gone = True
                raise DeviceLostError(f"{self.uri}: camera stopped answering while waiting "
                                      f"for control ({exc.message})") from None
            left = deadline - time.monotonic()
            if left <= 0 or self._stop.wait(min(CONTROL_RETRY_S, left)):
                break
        why = "stopped waiting" if self._stop.is_set() else (
            f"still held after {self.control_wait_s:g} s")
        raise DriverError(
            f"{self.uri}: camera is controlled by another client ({why}, heartbeat timeout "
            f"{heartbeat}); stop that program or power-cycle the camera, or wait longer "
            f"(--control-wait)"
        )

    def _configure(self) -> None:
        cam = self._cam
        continuous = _aravis().AcquisitionMode.CONTINUOUS
        self._call("acquisition mode", cam.set_acquisition_mode, continuous)
        self.disable_auto()
        self._select_format()
        if cam.is_gv_device():
            # Largest packet the path carries; falls back to the default size.
            self._call("packet size negotiation", cam.gv_auto_packet_size)
        self._exposure_s = self._call("exposure", cam.get_exposure_time) / 1e6

    def _select_format(self) -> None:
        cam = self._cam
        offered = list(self._call("pixel formats", cam.dup_available_pixel_formats_as_strings))
        if self.requested_format:
            if self.requested_format not in offered:
                raise DriverError(
                    f"{self.uri}: pixel format {self.requested_format} not offered "
                    f"(camera has {', '.join(offered)})"
                )
            if not supported_format(self.requested_format):
                raise DriverError(
                    f"{self.uri}: pixel format {self.requested_format} is not supported"
                )
            choice = self.requested_format
        else:
            usable = [f for f in PREFERRED_FORMATS if f in offered]
            if not usable:
                raise DriverError(
                    f"{self.uri}: none of the camera's pixel formats is supported "
                    f"(camera has {', '.join(offered)})"
                )
            choice = usable[0]
        self._call("pixel format", self._cam.set_pixel_format_from_string, choice)
        actual = self._call("pixel format", self._cam.get_pixel_format_as_string)
        if actual != choice:
            raise DriverError(f"{self.uri}: asked for pixel format {choice}, camera uses {actual}")
        self.pixel_format = actual

    def close(self) -> None:
        """Stop streaming, free the stream, then release the camera (safe to call twice).

        A camera that was lost cannot be released quickly: Aravis retries every
        transaction on its dead control channel for seconds.  Its stream and
        camera objects are then handed to a helper thread that frees them in
        the same order; :attr:`released` is set when that is done.
        """
        self._stop.set()
        if self._streaming_thread not in (None, threading.get_ident()):
            # frames() runs in another thread: let it leave its loop (it owns the stream).
            self._idle.wait(timeout=POP_TIMEOUT_S * 50)
        if self._dev is not None and self._lost_handler is not None:
            self._dev.disconnect(self._lost_handler)
        self._lost_handler = None
        if self._cam is None:
            return
        dead = self._gone or self._control_lost.is_set()
        # Without control (given up waiting for it) Aravis's goodbye write is refused,
        # or ignored for seconds: free it in the background too.
        slow = dead or (self._cam.is_gv_device() and not self._dev.is_controller())
        if self._stream is not None:
            self._last_stats = self._read_stats()
            if not dead:
                try:
                    self._cam.stop_acquisition()
                except _glib_error():
                    dead = True  # the camera went away just now
        # The only references to the Aravis objects move into `owned`.
        owned = [self._probe, self._stream, self._dev, self._cam]
        self._probe = self._stream = self._dev = self._cam = None
        self.released.clear()
        if slow:
            # daemon: freeing a dead camera can take Aravis seconds of retries,
            # which must not keep the process alive after it has reported the loss
            threading.Thread(target=_release, args=(owned, self.released),
                             name=f"{self.uri} release", daemon=True).start()
        else:
            _release(owned, self.released)

    def _end_stream(self) -> None:
        """Stop acquisition and free the stream, unless the camera is gone.

        A dead camera's stream is left to close(): freeing it takes seconds
        and DeviceLostError should reach the caller at once.
        """
        if self._stream is None:
            return
        self._last_stats = self._read_stats()
        if self._gone or self._control_lost.is_set():
            return
        try:
            self._cam.stop_acquisition()
        except _glib_error():
            self._gone = True
            return
        self._stream = None

    def _on_control_lost(self, *_args) -> None:
        # Called from Aravis's heartbeat thread.
        self._control_lost.set()

    def _call(self, what: str, fn, *args):
        if self._cam is None:
            raise DriverError(f"{self.uri}: camera is not open")
        try:
            return fn(*args)
        except _glib_error() as exc:
            raise DriverError(f"{self.uri}: {what}: {exc.message}") from None

    # -- controls ------------------------------------------------------------

    def disable_auto(self) -> None:
        """Switch auto exposure, auto gain and auto white balance off, and verify.

        Raises
        ------
        DriverError
            If the camera keeps any of them on.
        """
        cam, Aravis = self._cam, _aravis()
        if cam.is_exposure_auto_available():
            self._call("ExposureAuto", cam.set_exposure_time_auto, Aravis.Auto.OFF)
            if self._call("ExposureAuto", cam.get_exposure_time_auto) != Aravis.Auto.OFF:
                raise DriverError(f"{self.uri}: camera refuses to switch ExposureAuto off")
        if cam.is_gain_auto_available():
            self._call("GainAuto", cam.set_gain_auto, Aravis.Auto.OFF)
            if self._call("GainAuto", cam.get_gain_auto) != Aravis.Auto.OFF:
                raise DriverError(f"{self.uri}: camera refuses to switch GainAuto off")
        if self._call("BalanceWhiteAuto", cam.is_feature_available, "BalanceWhiteAuto"):
            self._call("BalanceWhiteAuto", cam.set_string, "BalanceWhiteAuto", "Off")
            if self._call("BalanceWhiteAuto", cam.get_string, "BalanceWhiteAuto") != "Off":
                raise DriverError(f"{self.uri}: camera refuses to switch BalanceWhiteAuto off")

    @property
    def exposure_s(self) -> float:
        return self._call("exposure", self._cam.get_exposure_time) / 1e6

    def set_exposure(self, seconds: float) -> float:
        """Set the exposure (ExposureTime or ExposureTimeAbs); return the read-back value."""
        lo, hi = self._call("exposure bounds", self._cam.get_exposure_time_bounds)
        us = seconds * 1e6
        if not lo <= us <= hi:
            raise DriverError(
                f"{self.uri}: exposure {seconds:g} s outside the camera's range "
                f"{lo / 1e6:g}..{hi / 1e6:g} s"
            )
        self._call("exposure", self._cam.set_exposure_time, us)
        self._exposure_s = self.exposure_s
        return self._exposure_s

    def set_gain(self, gain: float) -> float:
        """Set the analogue gain (camera units, usually dB) and return the read-back value."""
        if not self._cam.is_gain_available():
            raise DriverError(f"{self.uri}: camera has no gain control")
        self._call("gain", self._cam.set_gain, float(gain))
        return float(self._call("gain", self._cam.get_gain))

    def set_frame_rate(self, fps: float) -> float:
        """Set the acquisition frame rate and return the read-back value (frames/s)."""
        if not self._cam.is_frame_rate_available():
            raise DriverError(f"{self.uri}: camera has no frame rate control")
        self._call("frame rate", self._cam.set_frame_rate, float(fps))
        return float(self._call("frame rate", self._cam.get_frame_rate))

    @property
    def size(self) -> tuple[int, int]:
        region = self._call("region", self._cam.get_region)
        return int(region.width), int(region.height)

    def set_size(self, width: int, height: int) -> None:
        """Set the region of interest, centred on the sensor.

        Raises
        ------
        DriverError
            Naming both sizes when the camera cannot give ``width`` x ``height``.
        """
        cam = self._cam
        cur_w, cur_h = self.size
        if (width, height) == (cur_w, cur_h):
            return
        w_lo, w_hi = self._call("width bounds", cam.get_width_bounds)
        h_lo, h_hi = self._call("height bounds", cam.get_height_bounds)
        w_inc = max(1, self._call("width", cam.get_width_increment))
        h_inc = max(1, self._call("height", cam.get_height_increment))
        sensor = self._call("sensor size", cam.get_sensor_size)
        fits = w_lo <= width <= w_hi and h_lo <= height <= h_hi
        if not fits or width % w_inc or height % h_inc:
            raise DriverError(
                f"{self.uri}: camera image is {cur_w}x{cur_h}, cannot set {width}x{height} "
                f"(width {w_lo}..{w_hi} step {w_inc}, height {h_lo}..{h_hi} step {h_inc})"
            )
        x = y = 0
        if cam.is_region_offset_available():
            x_inc = max(1, self._call("offset", cam.get_x_offset_increment))
            y_inc = max(1, self._call("offset", cam.get_y_offset_increment))
            x = (sensor.width - width) // 2 // x_inc * x_inc
            y = (sensor.height - height) // 2 // y_inc * y_inc
        self._call("region", cam.set_region, x, y, width, height)
        got = self.size
        if got != (width, height):
            raise DriverError(
                f"{self.uri}: asked for image size {width}x{height}, camera gives {got[0]}x{got[1]}"
            )

    # -- streaming -----------------------------------------------------------

    def stop(self) -> None:
        """Make a running :meth:`frames` end within about 0.1 s (thread-safe)."""
        self._stop.set()
        self._handoff.wake()

    def frames(self) -> Iterator[Frame]:
        """Stream frames until :meth:`stop` or :meth:`close`.

        Buffers whose status is not success (missing packets, timeouts) are
        counted in :meth:`stats` and skipped.

        Raises
        ------
        DeviceLostError
            When the camera stops answering mid-stream.
        """
        if self._cam is None:
            raise DriverError(f"{self.uri}: camera is not open")
        self._stop.clear()
        self._idle.clear()
        self._streaming_thread = threading.get_ident()
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
                self._acq_thread.join()  # it leaves within one pop timeout
                self._acq_thread = None
            self._handoff.discard()  # copied out after stop(), or never asked for
            self._end_stream()
            self._streaming_thread = None
            self._idle.set()

    def _start_stream(self) -> None:
        Aravis = _aravis()
        self._bad_buffers = 0
        self._delivered = 0
        stream = self._call("stream", self._cam.create_stream, None, None)
        if stream is None:
            raise DriverError(f"{self.uri}: cannot create a stream")
        if isinstance(stream, Aravis.GvStream):
            # Kernel socket buffer sized to one frame: fewer lost packets at high rates.
            stream.set_property("socket-buffer", Aravis.GvStreamSocketBuffer.AUTO)
        payload = self._call("payload", self._cam.get_payload)
        self.pool_size = self._pool_size(payload)
        for _ in range(self.pool_size):
            stream.push_buffer(Aravis.Buffer.new_allocate(payload))
        self._handoff = FrameHandoff(self.max_pending_mib * 2**20)
        self._stream = stream
        self._call("start acquisition", self._cam.start_acquisition)

    def _pool_size(self, payload: int) -> int:
        """Buffers for ``buffer_s`` seconds of frames, at least 8, within ``max_buffer_mib``."""
        if self.n_buffers is not None:
            return self.n_buffers
        fps = 30.0
        if self._cam.is_frame_rate_available():
            try:
                fps = float(self._cam.get_frame_rate()) or fps
            except _glib_error():
                pass
        wanted = math.ceil(fps * self.buffer_s)
        cap = int(self.max_buffer_mib * 2**20 // max(1, payload))
        return max(MIN_BUFFERS, min(wanted, cap))

    def _acquire(self) -> None:
        """The acquisition thread: pop, copy out, push back; nothing else.

        No local reference to the stream: a DeviceLostError traceback keeps
        this frame alive, and close() must be what frees the stream.
        """
        error = None
        try:
            success = _aravis().BufferStatus.SUCCESS
            timeouts_for_lost = max(1, math.ceil(self.lost_after_s / POP_TIMEOUT_S))
            idle = 0
            while not self._stop.is_set():
                if self._control_lost.is_set():
                    raise self._lost("Aravis lost the control channel")
                buffer = self._stream.timeout_pop_buffer(int(POP_TIMEOUT_S * 1e6))
                if buffer is None:
                    idle += 1
                    if idle >= timeouts_for_lost:
                        if not self._control_answers():
                            raise self._lost(
                                f"no image for {idle * POP_TIMEOUT_S:.1f} s and the control "
                                f"channel does not answer"
                            )
                        idle = 0
                    continue
                idle = 0
                try:
                    if buffer.get_status() != success:
                        self._bad_buffers += 1
                        continue
                    # get_image_data returns new bytes: the copy is ours once the
                    # buffer goes back to the pool in `finally`
                    item = (
                        buffer.get_frame_id(),
                        buffer.get_image_data(),
                        buffer.get_image_width(),
                        buffer.get_image_height(),
                        buffer.get_image_padding()[0],
                        buffer.get_timestamp() or buffer.get_system_timestamp(),
                    )
                finally:
                    self._stream.push_buffer(buffer)
                    buffer = None
                self._handoff.put(item)
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer in _deliver
            error = exc
        finally:
            self._handoff.finish(error)

    def _deliver(self) -> Iterator[Frame]:
        """Convert and yield the copied-out frames, on the consumer's thread."""
        index = None
        last_id = None
        while True:
            item = self._handoff.get(self._stop)
            if item is None:
                return  # stopped, or the stream ended
            frame_id, data, width, height, padding, stamp_ns = item
            index = frame_id if index is None else index + _id_step(last_id, frame_id)
            last_id = frame_id
            image = convert_image(data, self.pixel_format, width, height, padding)
            self._delivered += 1
            yield Frame(index=index, timestamp=stamp_ns / 1e9, exposure_s=self._exposure_s,
                        image=image, bits=significant_bits(self.pixel_format))

    def _control_answers(self) -> bool:
        """Read a register with a deadline of ``probe_timeout_s``.

        Aravis retries a dead control channel for seconds; the read runs in a
        helper thread so that the verdict comes after the deadline instead.
        close() joins that thread before it frees the camera.
        """
        answered = threading.Event()
        ok = []

        def probe() -> None:
            try:
                self._dev.read_register(_PROBE_REGISTER)
                ok.append(True)
            except _glib_error():
                pass
            finally:
                answered.set()

        self._probe = threading.Thread(target=probe, name=f"{self.uri} probe", daemon=True)
        self._probe.start()
        if not answered.wait(self.probe_timeout_s):
            return False
        self._probe.join()
        return bool(ok) and not self._control_lost.is_set()

    def _lost(self, why: str) -> DeviceLostError:
        self._gone = True  # no more control transactions: each would time out
        return DeviceLostError(f"{self.uri}: camera lost after {self._delivered} frames ({why})")

    # -- statistics ----------------------------------------------------------

    def _read_stats(self) -> dict[str, float]:
        stream = self._stream
        out: dict[str, float] = {"delivered": float(self._delivered),
                                 "bad_buffers": float(self._bad_buffers),
                                 "dropped_in_driver": float(self._handoff.dropped),
                                 "discarded_at_stop": float(self._handoff.discarded),
                                 "buffers": float(self.pool_size)}
        if stream is None:
            return out
        from gi.repository import GObject

        # Every counter the transport has (GigE: missing/resent packets, ...);
        # get_statistics() is not usable through introspection.
        for i in range(stream.get_n_infos()):
            name = stream.get_info_name(i)
            key = _STAT_NAMES.get(name, name[2:] if name.startswith("n_") else name)
            if stream.get_info_type(i) == GObject.TYPE_UINT64:
                out[key] = float(stream.get_info_uint64(i))
            elif stream.get_info_type(i) == GObject.TYPE_DOUBLE:
                out[key] = float(stream.get_info_double(i))
        return out

    def stats(self) -> dict[str, float]:
        """Stream statistics: completed, failures, underruns, missing/resent packets, ...

        ``failures`` counts buffers Aravis could not complete; ``bad_buffers``
        those that reached :meth:`frames` with a non-success status.  After
        streaming ends the last values are kept.
        """
        if self._stream is not None:
            return self._read_stats()
        return dict(self._last_stats)


def _print_notice(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _release(owned: list, done: threading.Event) -> None:
    """Drop the last references to ``[probe, stream, device, camera]`` in that order.

    The stream must be freed before the camera: freeing the camera while the
    stream thread still runs hangs Aravis.
    """
    probe = owned.pop(0)
    if probe is not None:
        probe.join()  # it borrows the device
    while owned:
        owned.pop(0)
    done.set()


def _id_step(last: int | None, new: int) -> int:
    """Frames between two camera frame ids, unwrapping 16-bit GigE Vision block ids.

    GigE Vision 1.x block ids run 1..65535 and skip 0 on wrap-around.
    """
    if last is None:
        return 1
    if new > last:
        return new - last
    if last > 0xFF00 and new < 0x100:
        return (new - last) % 0xFFFF
    return 1  # the camera restarted its counter
