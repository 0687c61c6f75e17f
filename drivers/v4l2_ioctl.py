"""The thin V4L2 layer: linuxpy's kernel structs and ioctl numbers, and a swappable I/O object.

Layers, bottom up:

1. :class:`LinuxIO` — ``open`` / ``ioctl`` / ``mmap`` / ``wait_readable`` /
   ``close`` on real file descriptors.  Anything with these methods can stand
   in for it (tests use a fake, because no V4L2 device can exist there).
2. :class:`V4L2Device` — one typed method per ioctl.  Every call packs one of
   linuxpy's ctypes structs (``linuxpy.video.raw``: the layouts of
   ``linux/videodev2.h``, generated from the header, and its ``IOC`` request
   numbers and enums) into bytes, lets the I/O object run the ioctl on those
   bytes, and unpacks the answer: the I/O object only ever sees bytes.
3. :class:`lightflow.drivers.v4l2.V4L2Camera` — the camera on top.

Why linuxpy's structs but not its ``Device``: that object's swappable ``io``
supplies only ``open``, ``os`` and ``select`` (``linuxpy/io.py``); every ioctl
goes through ``fcntl.ioctl`` and every buffer through ``mmap.mmap`` on the real
file descriptor, so a test without a device could only patch linuxpy's
module internals (as linuxpy's own tests do).  Layer 1 here covers all five
operations, so tests swap it without patching anything, and nothing of the
kernel ABI is written by hand.  linuxpy is GPL-3.0-or-later.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import mmap
import os
import select
from typing import Protocol

from linuxpy.video import raw

# -- constants and structs: linuxpy's ---------------------------------------

BUF_TYPE_VIDEO_CAPTURE = int(raw.BufType.VIDEO_CAPTURE)
MEMORY_MMAP = int(raw.Memory.MMAP)
FIELD_NONE = int(raw.Field.NONE)

CAP_VIDEO_CAPTURE = int(raw.Capability.VIDEO_CAPTURE)
CAP_STREAMING = int(raw.Capability.STREAMING)
CAP_DEVICE_CAPS = int(raw.Capability.DEVICE_CAPS)
CAP_TIMEPERFRAME = int(raw.Capability.TIMEPERFRAME)

BUF_FLAG_ERROR = int(raw.BufferFlag.ERROR)
CTRL_FLAG_DISABLED = int(raw.ControlFlag.DISABLED)

FRMSIZE_TYPE_DISCRETE = int(raw.Frmsizetypes.DISCRETE)

CID_AUTO_WHITE_BALANCE = int(raw.ControlID.AUTO_WHITE_BALANCE)
CID_AUTOGAIN = int(raw.ControlID.AUTOGAIN)
CID_GAIN = int(raw.ControlID.GAIN)
CID_EXPOSURE_AUTO = int(raw.ControlID.EXPOSURE_AUTO)
CID_EXPOSURE_ABSOLUTE = int(raw.ControlID.EXPOSURE_ABSOLUTE)
EXPOSURE_AUTO = int(raw.ExposureAutoType.AUTO)
EXPOSURE_MANUAL = int(raw.ExposureAutoType.MANUAL)
#: V4L2_CID_EXPOSURE_ABSOLUTE counts in units of 100 µs
EXPOSURE_UNIT_S = 100e-6


def fourcc(code: str) -> int:
    """The V4L2 pixel format number of a four-character code (``"YUYV"``)."""
    a, b, c, d = code.encode("ascii")
    return a | b << 8 | c << 16 | d << 24


def fourcc_str(value: int) -> str:
    """The four-character code of a V4L2 pixel format number."""
    return bytes((value >> s) & 0xFF for s in (0, 8, 16, 24)).decode("ascii", "replace")


Capability = raw.v4l2_capability
FmtDesc = raw.v4l2_fmtdesc
PixFormat = raw.v4l2_pix_format
Format = raw.v4l2_format
Fract = raw.v4l2_fract
CaptureParm = raw.v4l2_captureparm
StreamParm = raw.v4l2_streamparm
QueryCtrl = raw.v4l2_queryctrl
Control = raw.v4l2_control
RequestBuffers = raw.v4l2_requestbuffers
Buffer = raw.v4l2_buffer
FrmSizeEnum = raw.v4l2_frmsizeenum


def _request(ioc: int) -> int:
    # linuxpy's numbers are signed C ints; the kernel's (and fcntl's) are unsigned
    return int(ioc) & 0xFFFFFFFF


VIDIOC_QUERYCAP = _request(raw.IOC.QUERYCAP)
VIDIOC_ENUM_FMT = _request(raw.IOC.ENUM_FMT)
VIDIOC_G_FMT = _request(raw.IOC.G_FMT)
VIDIOC_S_FMT = _request(raw.IOC.S_FMT)
VIDIOC_REQBUFS = _request(raw.IOC.REQBUFS)
VIDIOC_QUERYBUF = _request(raw.IOC.QUERYBUF)
VIDIOC_QBUF = _request(raw.IOC.QBUF)
VIDIOC_DQBUF = _request(raw.IOC.DQBUF)
VIDIOC_STREAMON = _request(raw.IOC.STREAMON)
VIDIOC_STREAMOFF = _request(raw.IOC.STREAMOFF)
VIDIOC_G_PARM = _request(raw.IOC.G_PARM)
VIDIOC_S_PARM = _request(raw.IOC.S_PARM)
VIDIOC_G_CTRL = _request(raw.IOC.G_CTRL)
VIDIOC_S_CTRL = _request(raw.IOC.S_CTRL)
VIDIOC_QUERYCTRL = _request(raw.IOC.QUERYCTRL)
VIDIOC_ENUM_FRAMESIZES = _request(raw.IOC.ENUM_FRAMESIZES)


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


def _text(field) -> str:
    return bytes(field).split(b"\0", 1)[0].decode("utf-8", "replace")


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
                sizes.append((fs.discrete.width, fs.discrete.height))
            else:
                sizes.append((fs.stepwise.max_width, fs.stepwise.max_height))
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
