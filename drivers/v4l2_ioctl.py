"""The thin V4L2 layer: kernel structs (ctypes), ioctl numbers, and a swappable I/O object.

Layers, bottom up (as in linuxpy):

1. :class:`LinuxIO` — ``open`` / ``ioctl`` / ``mmap`` / ``wait_readable`` /
   ``close`` on real file descriptors.  Anything with these methods can stand
   in for it (tests use a fake, because no V4L2 device can exist there).
2. :class:`V4L2Device` — one typed method per ioctl.  Every call packs a
   ctypes struct into bytes, lets the I/O object run the ioctl on those bytes,
   and unpacks the answer: the I/O object only ever sees bytes.
3. :class:`lightflow.drivers.v4l2.V4L2Camera` — the camera on top.

Struct layouts are those of ``linux/videodev2.h`` on 64-bit Linux.

Why not linuxpy itself (checked with linuxpy 0.25.0): its ``Device`` takes an
``io`` object, but that object only supplies ``open``, ``os`` and ``select``
(``linuxpy/io.py``, class ``IO``).  Every ioctl goes through the module
function ``linuxpy.ioctl.ioctl``, which calls ``fcntl.ioctl`` on the real file
descriptor, and buffers are mapped with ``mmap.mmap`` on it
(``linuxpy/video/device.py``, ``mem_map``).  A test without a V4L2 device can
only fake those by patching linuxpy's module internals, which is what
linuxpy's own tests do (``mock.patch("linuxpy.ioctl.fcntl.ioctl", ...)``,
``mock.patch("linuxpy.video.device.mmap.mmap", ...)`` in
``tests/test_video.py``).  This layer keeps the I/O object that covers all
five operations, so tests swap it without patching anything.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import mmap
import os
import select
from typing import Protocol

u8, u32, s32 = ctypes.c_uint8, ctypes.c_uint32, ctypes.c_int32

# -- constants --------------------------------------------------------------

BUF_TYPE_VIDEO_CAPTURE = 1
MEMORY_MMAP = 1
FIELD_NONE = 1

CAP_VIDEO_CAPTURE = 0x00000001
CAP_STREAMING = 0x04000000
CAP_DEVICE_CAPS = 0x80000000
CAP_TIMEPERFRAME = 0x1000

BUF_FLAG_ERROR = 0x40
CTRL_FLAG_DISABLED = 0x0001

FRMSIZE_TYPE_DISCRETE = 1

CID_BASE = 0x00980900
CID_AUTO_WHITE_BALANCE = CID_BASE + 12
CID_AUTOGAIN = CID_BASE + 18
CID_GAIN = CID_BASE + 19
CID_CAMERA_CLASS_BASE = 0x009A0900
CID_EXPOSURE_AUTO = CID_CAMERA_CLASS_BASE + 1
CID_EXPOSURE_ABSOLUTE = CID_CAMERA_CLASS_BASE + 2
EXPOSURE_AUTO = 0
EXPOSURE_MANUAL = 1
#: V4L2_CID_EXPOSURE_ABSOLUTE counts in units of 100 µs
EXPOSURE_UNIT_S = 100e-6


def fourcc(code: str) -> int:
    """The V4L2 pixel format number of a four-character code (``"YUYV"``)."""
    a, b, c, d = code.encode("ascii")
    return a | b << 8 | c << 16 | d << 24


def fourcc_str(value: int) -> str:
    """The four-character code of a V4L2 pixel format number."""
    return bytes((value >> s) & 0xFF for s in (0, 8, 16, 24)).decode("ascii", "replace")


# -- structs ----------------------------------------------------------------


class Capability(ctypes.Structure):
    _fields_ = [("driver", u8 * 16), ("card", u8 * 32), ("bus_info", u8 * 32),
                ("version", u32), ("capabilities", u32), ("device_caps", u32),
                ("reserved", u32 * 3)]  # fmt: skip


class FmtDesc(ctypes.Structure):
    _fields_ = [("index", u32), ("type", u32), ("flags", u32), ("description", u8 * 32),
                ("pixelformat", u32), ("mbus_code", u32), ("reserved", u32 * 3)]  # fmt: skip


class PixFormat(ctypes.Structure):
    _fields_ = [("width", u32), ("height", u32), ("pixelformat", u32), ("field", u32),
                ("bytesperline", u32), ("sizeimage", u32), ("colorspace", u32), ("priv", u32),
                ("flags", u32), ("ycbcr_enc", u32), ("quantization", u32),
                ("xfer_func", u32)]  # fmt: skip


class _FormatUnion(ctypes.Union):
    # The kernel union holds pointers (struct v4l2_window): 8-byte aligned.
    _fields_ = [("pix", PixFormat), ("raw_data", u8 * 200), ("_align", ctypes.c_void_p * 25)]


class Format(ctypes.Structure):
    _fields_ = [("type", u32), ("fmt", _FormatUnion)]


class Fract(ctypes.Structure):
    _fields_ = [("numerator", u32), ("denominator", u32)]


class CaptureParm(ctypes.Structure):
    _fields_ = [("capability", u32), ("capturemode", u32), ("timeperframe", Fract),
                ("extendedmode", u32), ("readbuffers", u32), ("reserved", u32 * 4)]  # fmt: skip


class _ParmUnion(ctypes.Union):
    _fields_ = [("capture", CaptureParm), ("raw_data", u8 * 200)]


class StreamParm(ctypes.Structure):
    _fields_ = [("type", u32), ("parm", _ParmUnion)]


class QueryCtrl(ctypes.Structure):
    _fields_ = [("id", u32), ("type", u32), ("name", u8 * 32), ("minimum", s32),
                ("maximum", s32), ("step", s32), ("default_value", s32), ("flags", u32),
                ("reserved", u32 * 2)]  # fmt: skip


class Control(ctypes.Structure):
    _fields_ = [("id", u32), ("value", s32)]


class RequestBuffers(ctypes.Structure):
    _fields_ = [("count", u32), ("type", u32), ("memory", u32), ("capabilities", u32),
                ("flags", u8), ("reserved", u8 * 3)]  # fmt: skip


class TimeVal(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_usec", ctypes.c_long)]


class TimeCode(ctypes.Structure):
    _fields_ = [("type", u32), ("flags", u32), ("frames", u8), ("seconds", u8),
                ("minutes", u8), ("hours", u8), ("userbits", u8 * 4)]  # fmt: skip


class _BufferM(ctypes.Union):
    _fields_ = [("offset", u32), ("userptr", ctypes.c_ulong), ("planes", ctypes.c_void_p),
                ("fd", s32)]  # fmt: skip


class Buffer(ctypes.Structure):
    _fields_ = [("index", u32), ("type", u32), ("bytesused", u32), ("flags", u32),
                ("field", u32), ("timestamp", TimeVal), ("timecode", TimeCode),
                ("sequence", u32), ("memory", u32), ("m", _BufferM), ("length", u32),
                ("reserved2", u32), ("request_fd", s32)]  # fmt: skip


class FrmSizeDiscrete(ctypes.Structure):
    _fields_ = [("width", u32), ("height", u32)]


class FrmSizeStepwise(ctypes.Structure):
    _fields_ = [("min_width", u32), ("max_width", u32), ("step_width", u32),
                ("min_height", u32), ("max_height", u32), ("step_height", u32)]  # fmt: skip


class _FrmSizeUnion(ctypes.Union):
    _fields_ = [("discrete", FrmSizeDiscrete), ("stepwise", FrmSizeStepwise)]


class FrmSizeEnum(ctypes.Structure):
    _fields_ = [("index", u32), ("pixel_format", u32), ("type", u32), ("size", _FrmSizeUnion),
                ("reserved", u32 * 2)]  # fmt: skip


# -- ioctl numbers (asm-generic/ioctl.h) ------------------------------------

_IOC_WRITE, _IOC_READ = 1, 2


def _ioc(direction: int, nr: int, struct: type) -> int:
    return direction << 30 | ctypes.sizeof(struct) << 16 | ord("V") << 8 | nr


VIDIOC_QUERYCAP = _ioc(_IOC_READ, 0, Capability)
VIDIOC_ENUM_FMT = _ioc(_IOC_READ | _IOC_WRITE, 2, FmtDesc)
VIDIOC_G_FMT = _ioc(_IOC_READ | _IOC_WRITE, 4, Format)
VIDIOC_S_FMT = _ioc(_IOC_READ | _IOC_WRITE, 5, Format)
VIDIOC_REQBUFS = _ioc(_IOC_READ | _IOC_WRITE, 8, RequestBuffers)
VIDIOC_QUERYBUF = _ioc(_IOC_READ | _IOC_WRITE, 9, Buffer)
VIDIOC_QBUF = _ioc(_IOC_READ | _IOC_WRITE, 15, Buffer)
VIDIOC_DQBUF = _ioc(_IOC_READ | _IOC_WRITE, 17, Buffer)
VIDIOC_STREAMON = _ioc(_IOC_WRITE, 18, ctypes.c_int)
VIDIOC_STREAMOFF = _ioc(_IOC_WRITE, 19, ctypes.c_int)
VIDIOC_G_PARM = _ioc(_IOC_READ | _IOC_WRITE, 21, StreamParm)
VIDIOC_S_PARM = _ioc(_IOC_READ | _IOC_WRITE, 22, StreamParm)
VIDIOC_G_CTRL = _ioc(_IOC_READ | _IOC_WRITE, 27, Control)
VIDIOC_S_CTRL = _ioc(_IOC_READ | _IOC_WRITE, 28, Control)
VIDIOC_QUERYCTRL = _ioc(_IOC_READ | _IOC_WRITE, 36, QueryCtrl)
VIDIOC_ENUM_FRAMESIZES = _ioc(_IOC_READ | _IOC_WRITE, 74, FrmSizeEnum)


# -- the I/O object -----------------------------------------------------------


class DeviceIO(Protocol):
    """What :class:`V4L2Device` needs from the operating system."""

    def open(self, path: str) -> int: ...

    def close(self, fd: int) -> None: ...

    def ioctl(self, fd: int, request: int, arg: bytearray) -> None:
        """Run ``request`` on ``arg`` in place; raise OSError with the errno on failure."""

    def mmap(self, fd: int, length: int, offset: int) -> mmap.mmap: ...

    def wait_readable(self, fd: int, timeout: float) -> bool:
        """Wait until a buffer can be dequeued; False after ``timeout`` seconds."""


class LinuxIO:
    """The real I/O: file descriptors, ``fcntl.ioctl``, ``mmap`` and ``select``."""

    def open(self, path: str) -> int:
        # Non-blocking: DQBUF answers EAGAIN, and waiting happens in select()
        # with a timeout, so that stop() is noticed.
        return os.open(path, os.O_RDWR | os.O_NONBLOCK | os.O_CLOEXEC)

    def close(self, fd: int) -> None:
        os.close(fd)

    def ioctl(self, fd: int, request: int, arg: bytearray) -> None:
        while True:
            try:
                fcntl.ioctl(fd, request, arg, True)
                return
            except InterruptedError:
                continue

    def mmap(self, fd: int, length: int, offset: int) -> mmap.mmap:
        return mmap.mmap(fd, length, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE,
                         offset=offset)

    def wait_readable(self, fd: int, timeout: float) -> bool:
        readable, _, failed = select.select([fd], [], [fd], timeout)
        return bool(readable or failed)


# -- typed ioctls -------------------------------------------------------------


def _text(raw) -> str:
    return bytes(raw).split(b"\0", 1)[0].decode("utf-8", "replace")


class V4L2Device:
    """One open V4L2 device node, one method per ioctl.

    Methods raise :class:`OSError` as the kernel reports it; the camera layer
    turns those into one-line DriverErrors.
    """

    def __init__(self, path: str, io: DeviceIO | None = None) -> None:
        self.path = path
        self.io = io if io is not None else LinuxIO()
        self.fd = self.io.open(path)

    def close(self) -> None:
        if self.fd >= 0:
            self.io.close(self.fd)
            self.fd = -1

    def _ioctl(self, request: int, struct: ctypes.Structure):
        buf = bytearray(bytes(struct))
        self.io.ioctl(self.fd, request, buf)
        return type(struct).from_buffer_copy(buf)

    # capability and formats

    def querycap(self) -> tuple[str, str, str, int]:
        """``(driver, card, bus_info, capabilities)``, with the per-node caps if given."""
        cap = self._ioctl(VIDIOC_QUERYCAP, Capability())
        caps = cap.device_caps if cap.capabilities & CAP_DEVICE_CAPS else cap.capabilities
        return _text(cap.driver), _text(cap.card), _text(cap.bus_info), caps

    def enum_formats(self) -> list[tuple[str, str]]:
        """Capture pixel formats as ``(fourcc, description)``."""
        found = []
        for index in range(256):
            try:
                desc = self._ioctl(VIDIOC_ENUM_FMT,
                                   FmtDesc(index=index, type=BUF_TYPE_VIDEO_CAPTURE))
            except OSError as exc:
                if exc.errno == errno.EINVAL:  # end of the list
                    break
                raise
            found.append((fourcc_str(desc.pixelformat), _text(desc.description)))
        return found

    def enum_framesizes(self, code: str) -> list[tuple[int, int]]:
        """Discrete frame sizes of a format; for a stepwise range, its largest size."""
        sizes = []
        for index in range(256):
            try:
                fs = self._ioctl(VIDIOC_ENUM_FRAMESIZES,
                                 FrmSizeEnum(index=index, pixel_format=fourcc(code)))
            except OSError as exc:
                if exc.errno == errno.EINVAL:
                    break
                raise
            if fs.type == FRMSIZE_TYPE_DISCRETE:
                sizes.append((fs.size.discrete.width, fs.size.discrete.height))
            else:
                sizes.append((fs.size.stepwise.max_width, fs.size.stepwise.max_height))
                break
        return sizes

    def g_fmt(self) -> PixFormat:
        return self._ioctl(VIDIOC_G_FMT, Format(type=BUF_TYPE_VIDEO_CAPTURE)).fmt.pix

    def s_fmt(self, code: str, width: int, height: int) -> PixFormat:
        """Ask for a format; returns what the driver chose (it may adjust)."""
        fmt = Format(type=BUF_TYPE_VIDEO_CAPTURE)
        fmt.fmt.pix.width, fmt.fmt.pix.height = width, height
        fmt.fmt.pix.pixelformat = fourcc(code)
        fmt.fmt.pix.field = FIELD_NONE
        return self._ioctl(VIDIOC_S_FMT, fmt).fmt.pix

    def g_parm(self) -> CaptureParm:
        return self._ioctl(VIDIOC_G_PARM, StreamParm(type=BUF_TYPE_VIDEO_CAPTURE)).parm.capture

    def s_parm(self, numerator: int, denominator: int) -> CaptureParm:
        """Set the time per frame; returns the driver's answer."""
        parm = StreamParm(type=BUF_TYPE_VIDEO_CAPTURE)
        parm.parm.capture.timeperframe = Fract(numerator, denominator)
        return self._ioctl(VIDIOC_S_PARM, parm).parm.capture

    # controls

    def queryctrl(self, cid: int) -> QueryCtrl | None:
        """The control's description, or None if the device lacks it (or it is disabled)."""
        try:
            ctrl = self._ioctl(VIDIOC_QUERYCTRL, QueryCtrl(id=cid))
        except OSError as exc:
            if exc.errno == errno.EINVAL:
                return None
            raise
        return None if ctrl.flags & CTRL_FLAG_DISABLED else ctrl

    def g_ctrl(self, cid: int) -> int:
        return self._ioctl(VIDIOC_G_CTRL, Control(id=cid)).value

    def s_ctrl(self, cid: int, value: int) -> None:
        self._ioctl(VIDIOC_S_CTRL, Control(id=cid, value=value))

    # buffers and streaming

    def reqbufs(self, count: int) -> int:
        """Request ``count`` mmap buffers (0 frees them); returns how many the driver gave."""
        req = RequestBuffers(count=count, type=BUF_TYPE_VIDEO_CAPTURE, memory=MEMORY_MMAP)
        return self._ioctl(VIDIOC_REQBUFS, req).count

    def querybuf(self, index: int) -> Buffer:
        return self._ioctl(VIDIOC_QUERYBUF, Buffer(index=index, type=BUF_TYPE_VIDEO_CAPTURE,
                                                   memory=MEMORY_MMAP))

    def qbuf(self, index: int) -> None:
        self._ioctl(VIDIOC_QBUF, Buffer(index=index, type=BUF_TYPE_VIDEO_CAPTURE,
                                        memory=MEMORY_MMAP))

    def dqbuf(self) -> Buffer | None:
        """A filled buffer, or None if none is ready yet (EAGAIN)."""
        try:
            return self._ioctl(VIDIOC_DQBUF, Buffer(type=BUF_TYPE_VIDEO_CAPTURE,
                                                    memory=MEMORY_MMAP))
        except BlockingIOError:
            return None

    def streamon(self) -> None:
        self._ioctl(VIDIOC_STREAMON, ctypes.c_int(BUF_TYPE_VIDEO_CAPTURE))

    def streamoff(self) -> None:
        self._ioctl(VIDIOC_STREAMOFF, ctypes.c_int(BUF_TYPE_VIDEO_CAPTURE))

    def mmap(self, buffer: Buffer) -> mmap.mmap:
        return self.io.mmap(self.fd, buffer.length, buffer.m.offset)

    def wait_readable(self, timeout: float) -> bool:
        return self.io.wait_readable(self.fd, timeout)
