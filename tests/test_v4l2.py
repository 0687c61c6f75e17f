"""The V4L2 driver, run through its real code path against a fake of the ioctl I/O layer."""

from __future__ import annotations

import ctypes
import errno
import mmap
import threading
import time
from collections import deque

import cv2
import numpy as np
import pytest

from lightflow.app.core.errors import DeviceLostError, DriverError
from lightflow.drivers import v4l2_ioctl as v
from lightflow.drivers.v4l2 import V4L2Camera, convert_frame, list_v4l2_devices

FD = 7


def colour_bars(width: int, height: int) -> np.ndarray:
    """Eight colour bars over a vertical brightness ramp; constant over pixel pairs."""
    bars = np.array([[255, 255, 255], [255, 255, 0], [0, 255, 255], [0, 255, 0],
                     [255, 0, 255], [255, 0, 0], [0, 0, 255], [40, 40, 40]], np.float64)
    cols = bars[(np.arange(width) * 8) // width]
    ramp = np.linspace(0.4, 1.0, height)[:, None, None]
    return np.round(cols[None] * ramp).astype(np.uint8)


def rgb_to_yuyv(rgb: np.ndarray) -> bytes:
    """BT.601 limited-range YUYV, chroma averaged over pixel pairs."""
    f = rgb.astype(np.float64)
    r, g, b = f[..., 0], f[..., 1], f[..., 2]
    y = 16 + (65.481 * r + 128.553 * g + 24.966 * b) / 255
    u = 128 + (-37.797 * r - 74.203 * g + 112.0 * b) / 255
    w = 128 + (112.0 * r - 93.786 * g - 18.214 * b) / 255
    out = np.empty(rgb.shape[:2] + (2,), np.float64)
    out[..., 0] = y
    out[:, 0::2, 1] = (u[:, 0::2] + u[:, 1::2]) / 2
    out[:, 1::2, 1] = (w[:, 0::2] + w[:, 1::2]) / 2
    return np.clip(np.round(out), 0, 255).astype(np.uint8).tobytes()


class FakeV4L2IO:
    """A fake of the V4L2 I/O layer (``open``/``ioctl``/``mmap``/``wait_readable``/``close``).

    It is a fake because no V4L2 device can exist on the test machine (its kernel
    has no module support: no /dev/video*, no vivid, no v4l2loopback).  It
    answers each ioctl at the byte level, reading and writing the kernel's
    struct layouts in the caller's buffer and failing with the kernel's errno
    values (EINVAL at the end of an enumeration, EAGAIN when no buffer is ready,
    ENODEV once unplugged), so that V4L2Camera's real format negotiation,
    controls, buffer queue and conversions run.  Frames are ``image`` encoded in
    the negotiated format, in anonymous mmaps standing in for the driver's.

    Like a real device it has a clock: once streaming, frame ``k`` is due at
    ``k`` frame periods after STREAMON.  A frame fills the oldest queued buffer;
    with no buffer queued it is lost (``lost_frames``) and its sequence number
    skipped, as a kernel driver does when the application starves it.
    """

    #: most buffers REQBUFS grants (the kernel's VIDEO_MAX_FRAME; uvcvideo's limit)
    MAX_BUFFERS = 32

    def __init__(self, image: np.ndarray, formats=("YUYV", "MJPG", "RGB3"),
                 sizes=((640, 480), (320, 240)), row_padding: int = 0, path="/dev/video0",
                 denied=(), refuse_autogain=False) -> None:
        self.image, self.formats, self.sizes = image, list(formats), list(sizes)
        self.row_padding, self.path, self.denied = row_padding, path, set(denied)
        self.refuse_autogain = refuse_autogain
        self.open_fds: set[int] = set()
        self.code, (self.width, self.height) = self.formats[0], self.sizes[0]
        # cid -> [minimum, maximum, step, default, value]
        self.controls = {v.CID_EXPOSURE_AUTO: [0, 3, 1, 3, 3],
                         v.CID_EXPOSURE_ABSOLUTE: [3, 2047, 1, 250, 250],
                         v.CID_AUTOGAIN: [0, 1, 1, 1, 1],
                         v.CID_GAIN: [0, 255, 1, 32, 32],
                         v.CID_AUTO_WHITE_BALANCE: [0, 1, 1, 1, 1]}
        self.period = (1, 30)
        self.maps: list[mmap.mmap] = []
        self.queued: deque[int] = deque()
        self.done: deque[tuple[int, int]] = deque()  # (buffer index, sequence) filled
        self.streaming = False
        self.sequence = 0  # the next frame's number on the device clock
        self.t0 = 0.0
        self.lost_frames = 0
        self.dequeued = 0
        self.error_frames: set[int] = set()
        self.truncated_frames: set[int] = set()  # sent cut short (a broken MJPG frame)
        self.unplugged = False
        self.lock = threading.RLock()  # the acquisition thread and the test's both call in
        self.changed = threading.Condition(self.lock)
        self._encoded: dict[tuple, bytes] = {}

    # -- the I/O interface --------------------------------------------------

    def open(self, path: str) -> int:
        if path in self.denied:
            raise PermissionError(errno.EACCES, "Permission denied", path)
        if path != self.path:
            raise FileNotFoundError(errno.ENOENT, "No such file or directory", path)
        self.open_fds.add(FD)
        return FD

    def close(self, fd: int) -> None:
        self.open_fds.remove(fd)
        self.streaming = False
        self.maps.clear()

    def mmap(self, fd: int, length: int, offset: int) -> mmap.mmap:
        index = offset // self.buffer_size
        assert fd == FD and offset % self.buffer_size == 0 and length == self.buffer_size
        return self.maps[index]

    def wait_readable(self, fd: int, timeout: float) -> bool:
        end = time.monotonic() + timeout
        with self.lock:
            while True:
                self._advance()
                if self.done or self.unplugged:
                    return True
                now = time.monotonic()
                if now >= end:
                    return False
                due = self.t0 + self.sequence * self.period_s if self.streaming else end
                # the device's clock: sleep until the next frame is due (or unplug/STREAMOFF)
                self.changed.wait(max(0.0, min(end, due) - now))

    def ioctl(self, fd: int, request: int, arg: bytearray) -> None:
        assert fd in self.open_fds and isinstance(arg, bytearray)
        handlers = {v.VIDIOC_QUERYCAP: self._querycap, v.VIDIOC_ENUM_FMT: self._enum_fmt,
                    v.VIDIOC_ENUM_FRAMESIZES: self._enum_framesizes,
                    v.VIDIOC_G_FMT: self._g_fmt, v.VIDIOC_S_FMT: self._s_fmt,
                    v.VIDIOC_G_PARM: self._g_parm, v.VIDIOC_S_PARM: self._s_parm,
                    v.VIDIOC_QUERYCTRL: self._queryctrl, v.VIDIOC_G_CTRL: self._g_ctrl,
                    v.VIDIOC_S_CTRL: self._s_ctrl, v.VIDIOC_REQBUFS: self._reqbufs,
                    v.VIDIOC_QUERYBUF: self._querybuf, v.VIDIOC_QBUF: self._qbuf,
                    v.VIDIOC_DQBUF: self._dqbuf, v.VIDIOC_STREAMON: self._streamon,
                    v.VIDIOC_STREAMOFF: self._streamoff}
        if self.unplugged:
            raise OSError(errno.ENODEV, "No such device")
        if request not in handlers:
            raise OSError(errno.ENOTTY, "Inappropriate ioctl for device")
        size = (request >> 16) & 0x3FFF
        assert len(arg) == size, f"ioctl {request:#x}: {len(arg)} bytes, expected {size}"
        with self.lock:
            handlers[request](arg)

    # -- what the test controls -----------------------------------------------

    @property
    def period_s(self) -> float:
        return self.period[0] / self.period[1]

    def unplug(self) -> None:
        with self.lock:
            self.unplugged = True
            self.changed.notify_all()

    def wait_dequeued(self, n: int, timeout: float = 30.0) -> bool:
        """Wait until ``n`` frames in all were dequeued (the test's view of the stream)."""
        with self.lock:
            return self.changed.wait_for(lambda: self.dequeued >= n, timeout)

    def expected_image(self) -> np.ndarray:
        return cv2.resize(self.image, (self.width, self.height), interpolation=cv2.INTER_NEAREST)

    # -- ioctl handlers ---------------------------------------------------------

    @staticmethod
    def _einval() -> OSError:
        return OSError(errno.EINVAL, "Invalid argument")

    def _querycap(self, arg):
        cap = v.Capability.from_buffer(arg)
        cap.driver = b"uvcvideo"
        cap.card = b"Fake webcam"
        cap.bus_info = b"usb-0000:00:1"
        cap.device_caps = v.CAP_VIDEO_CAPTURE | v.CAP_STREAMING
        cap.capabilities = cap.device_caps | v.CAP_DEVICE_CAPS

    def _enum_fmt(self, arg):
        desc = v.FmtDesc.from_buffer(arg)
        if desc.type != v.BUF_TYPE_VIDEO_CAPTURE or desc.index >= len(self.formats):
            raise self._einval()
        desc.pixelformat = v.fourcc(self.formats[desc.index])
        desc.description = self.formats[desc.index].encode()

    def _enum_framesizes(self, arg):
        fs = v.FrmSizeEnum.from_buffer(arg)
        if v.fourcc_str(fs.pixel_format) not in self.formats or fs.index >= len(self.sizes):
            raise self._einval()
        fs.type = v.FRMSIZE_TYPE_DISCRETE
        fs.discrete.width, fs.discrete.height = self.sizes[fs.index]

    @property
    def bytesperline(self) -> int:
        return {"YUYV": 2, "RGB3": 3, "MJPG": 0}[self.code] * self.width + (
            self.row_padding if self.code != "MJPG" else 0)

    @property
    def buffer_size(self) -> int:
        if self.code == "MJPG":
            return self.width * self.height * 2
        return self.bytesperline * self.height

    def _fill_pix(self, pix):
        pix.width, pix.height, pix.pixelformat = self.width, self.height, v.fourcc(self.code)
        pix.field, pix.bytesperline, pix.sizeimage = 1, self.bytesperline, self.buffer_size

    def _g_fmt(self, arg):
        fmt = v.Format.from_buffer(arg)
        if fmt.type != v.BUF_TYPE_VIDEO_CAPTURE:
            raise self._einval()
        self._fill_pix(fmt.fmt.pix)

    def _s_fmt(self, arg):
        if self.maps:
            raise OSError(errno.EBUSY, "Device or resource busy")
        fmt = v.Format.from_buffer(arg)
        pix = fmt.fmt.pix
        code = v.fourcc_str(pix.pixelformat)
        # Like real drivers: an unknown format falls back, a size snaps to the nearest.
        self.code = code if code in self.formats else self.formats[0]
        self.width, self.height = min(
            self.sizes, key=lambda s: abs(s[0] - pix.width) + abs(s[1] - pix.height))
        self._fill_pix(pix)

    def _g_parm(self, arg):
        parm = v.StreamParm.from_buffer(arg)
        parm.parm.capture.capability = v.CAP_TIMEPERFRAME
        parm.parm.capture.timeperframe.numerator, parm.parm.capture.timeperframe.denominator = (
            self.period)

    def _s_parm(self, arg):
        parm = v.StreamParm.from_buffer(arg)
        tpf = parm.parm.capture.timeperframe
        fps = tpf.denominator / tpf.numerator
        self.period = (1, min((15, 30, 60), key=lambda f: abs(f - fps)))
        self._g_parm(arg)

    def _queryctrl(self, arg):
        q = v.QueryCtrl.from_buffer(arg)
        if q.id not in self.controls:
            raise self._einval()
        q.minimum, q.maximum, q.step, q.default_value, _ = self.controls[q.id]
        q.type = 1

    def _g_ctrl(self, arg):
        c = v.Control.from_buffer(arg)
        if c.id not in self.controls:
            raise self._einval()
        c.value = self.controls[c.id][4]

    def _s_ctrl(self, arg):
        c = v.Control.from_buffer(arg)
        if c.id not in self.controls:
            raise self._einval()
        lo, hi, step, _, _ = self.controls[c.id]
        if not lo <= c.value <= hi or (c.value - lo) % step:
            raise OSError(errno.ERANGE, "Numerical result out of range")
        if c.id == v.CID_AUTOGAIN and self.refuse_autogain:
            return  # accepted, silently ignored (some cheap webcams do this)
        self.controls[c.id][4] = c.value

    def _reqbufs(self, arg):
        req = v.RequestBuffers.from_buffer(arg)
        if req.memory != v.MEMORY_MMAP or req.type != v.BUF_TYPE_VIDEO_CAPTURE:
            raise self._einval()
        if self.streaming:
            raise OSError(errno.EBUSY, "Device or resource busy")
        self.maps = [mmap.mmap(-1, self.buffer_size)
                     for _ in range(min(req.count, self.MAX_BUFFERS))]
        self.queued.clear()
        self.done.clear()
        req.count = len(self.maps)

    def _buffer(self, arg):
        buf = v.Buffer.from_buffer(arg)
        if buf.memory != v.MEMORY_MMAP or buf.index >= len(self.maps):
            raise self._einval()
        return buf

    def _querybuf(self, arg):
        buf = self._buffer(arg)
        buf.length, buf.m.offset = self.buffer_size, buf.index * self.buffer_size

    def _qbuf(self, arg):
        buf = self._buffer(arg)
        if buf.index in self.queued or any(i == buf.index for i, _ in self.done):
            raise self._einval()
        self._advance()  # frames due before now could not use this buffer
        self.queued.append(buf.index)

    def _advance(self) -> None:
        """Run the device clock up to now: each due frame fills a queued buffer or is lost."""
        if not self.streaming:
            return
        now = time.monotonic()
        while self.t0 + self.sequence * self.period_s <= now:
            if self.queued:
                index = self.queued.popleft()
                data = self._encode()
                self.maps[index][: len(data)] = data
                self.done.append((index, self.sequence))
            else:
                self.lost_frames += 1
            self.sequence += 1

    def _encode(self) -> bytes:
        key = (self.code, self.width, self.height, self.row_padding)
        if key not in self._encoded:
            self._encoded[key] = self._encode_now()
        return self._encoded[key]

    def _encode_now(self) -> bytes:
        rgb = self.expected_image()
        if self.code == "MJPG":
            ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                                   [cv2.IMWRITE_JPEG_QUALITY, 95])
            return jpg.tobytes()
        raw = rgb.tobytes() if self.code == "RGB3" else rgb_to_yuyv(rgb)
        rows = np.frombuffer(raw, np.uint8).reshape(self.height, -1)
        pad = np.zeros((self.height, self.row_padding), np.uint8)
        return np.hstack([rows, pad]).tobytes()

    def _dqbuf(self, arg):
        buf = v.Buffer.from_buffer(arg)
        if not self.streaming:
            raise self._einval()
        self._advance()
        if not self.done:
            raise BlockingIOError(errno.EAGAIN, "Resource temporarily unavailable")
        index, sequence = self.done.popleft()
        used = 100 if sequence in self.truncated_frames else len(self._encode())
        buf.index, buf.bytesused, buf.sequence = index, used, sequence
        buf.flags = v.BUF_FLAG_ERROR if sequence in self.error_frames else 0
        t = sequence * self.period_s
        buf.timestamp.secs, buf.timestamp.usecs = int(t), round((t % 1) * 1e6)
        buf.field, buf.length = 1, self.buffer_size
        self.dequeued += 1
        self.changed.notify_all()

    def _streamon(self, arg):
        if ctypes.c_int.from_buffer(arg).value != v.BUF_TYPE_VIDEO_CAPTURE or not self.maps:
            raise self._einval()
        self.streaming = True
        self.t0, self.sequence = time.monotonic(), 0

    def _streamoff(self, arg):
        self.streaming = False
        self.queued.clear()
        self.done.clear()
        self.changed.notify_all()


# -- the ioctl layer matches the kernel's ---------------------------------------

# From linux/videodev2.h on x86-64 (printed by a C program with the real header).
KERNEL = {"VIDIOC_QUERYCAP": 0x80685600, "VIDIOC_ENUM_FMT": 0xC0405602,
          "VIDIOC_G_FMT": 0xC0D05604, "VIDIOC_S_FMT": 0xC0D05605, "VIDIOC_REQBUFS": 0xC0145608,
          "VIDIOC_QUERYBUF": 0xC0585609, "VIDIOC_QBUF": 0xC058560F, "VIDIOC_DQBUF": 0xC0585611,
          "VIDIOC_STREAMON": 0x40045612, "VIDIOC_STREAMOFF": 0x40045613,
          "VIDIOC_G_PARM": 0xC0CC5615, "VIDIOC_S_PARM": 0xC0CC5616, "VIDIOC_G_CTRL": 0xC008561B,
          "VIDIOC_S_CTRL": 0xC008561C, "VIDIOC_QUERYCTRL": 0xC0445624,
          "VIDIOC_ENUM_FRAMESIZES": 0xC02C564A}


def test_ioctl_numbers_and_layouts_match_kernel():
    for name, number in KERNEL.items():
        assert getattr(v, name) == number, name
    assert (v.Buffer.timestamp.offset, v.Buffer.sequence.offset, v.Buffer.memory.offset,
            v.Buffer.m.offset, v.Buffer.length.offset) == (24, 56, 60, 64, 72)
    assert v.Format.fmt.offset == 8 and v.FmtDesc.pixelformat.offset == 44
    assert v.QueryCtrl.minimum.offset == 40 and v.QueryCtrl.flags.offset == 56
    assert v.CaptureParm.timeperframe.offset == 8 and v.FrmSizeEnum.m1.offset == 12
    assert (v.fourcc("YUYV"), v.fourcc("MJPG"), v.fourcc("RGB3")) == (
        0x56595559, 0x47504A4D, 0x33424752)
    assert (v.CID_EXPOSURE_AUTO, v.CID_EXPOSURE_ABSOLUTE, v.CID_AUTOGAIN,
            v.CID_AUTO_WHITE_BALANCE) == (0x9A0901, 0x9A0902, 0x980912, 0x98090C)


# -- conversions ----------------------------------------------------------------


def test_convert_known_images():
    rgb = colour_bars(64, 16)
    assert np.array_equal(convert_frame(rgb.tobytes(), "RGB3", 64, 16), rgb)
    yuyv = convert_frame(rgb_to_yuyv(rgb), "YUYV", 64, 16)
    assert np.abs(yuyv.astype(int) - rgb).max() <= 3
    ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                           [cv2.IMWRITE_JPEG_QUALITY, 100])
    mjpg = convert_frame(jpg.tobytes(), "MJPG", 64, 16)
    # JPEG subsamples chroma: compare away from the bar edges.
    inner = np.abs(mjpg.astype(int) - rgb)[:, [2, 3, 4, 5, 10, 11, 12, 13, 18, 19, 20, 21]]
    assert inner.max() <= 12
    with pytest.raises(DriverError, match="MJPG frame is 64x16, expected 32x16"):
        convert_frame(jpg.tobytes(), "MJPG", 32, 16)
    with pytest.raises(DriverError, match="needs 6144 bytes, got 100"):
        convert_frame(bytes(100), "RGB3", 64, 32)


# -- the camera over the fake ------------------------------------------------------


@pytest.fixture
def image():
    return colour_bars(640, 480)


def grab(cam: V4L2Camera, n: int):
    frames = []
    for frame in cam.frames():
        frames.append(frame)
        if len(frames) == n:
            break
    return frames


@pytest.mark.parametrize("code,tolerance", [("RGB3", 0), ("YUYV", 3), ("MJPG", 0)])
def test_stream_each_format(image, code, tolerance):
    io = FakeV4L2IO(image, formats=("MJPG", "YUYV", "RGB3"), row_padding=8)
    with V4L2Camera("/dev/video0", pixel_format=code, io=io) as cam:
        assert cam.pixel_format == code and cam.size == (640, 480)
        frames = grab(cam, 12)
        stats = cam.stats()
        assert stats["delivered"] == 12 and stats["buffers"] == 30  # 1 s at 30 fps
        assert stats["failures"] == stats["missing_frames"] == stats["bad_buffers"] == 0
        assert stats["dropped_in_driver"] == 0 and io.lost_frames == 0
        assert not io.streaming and not io.maps  # STREAMOFF and REQBUFS(0) on the way out
    assert not io.open_fds
    assert [f.index for f in frames] == list(range(12))
    assert [f.timestamp for f in frames] == pytest.approx(np.arange(12) / 30, abs=1e-6)
    expected = io.expected_image().astype(int)
    # MJPG is lossy: each frame must be exactly what the device's JPEG decodes to.
    reference = expected if code != "MJPG" else cv2.cvtColor(
        cv2.imdecode(np.frombuffer(io._encode(), np.uint8), cv2.IMREAD_COLOR),
        cv2.COLOR_BGR2RGB).astype(int)
    for frame in frames:
        assert frame.image.shape == (480, 640, 3) and frame.image.dtype == np.uint8
        assert np.abs(frame.image.astype(int) - reference).max() <= tolerance
        assert np.abs(frame.image.astype(int) - expected).mean() < 2
    # Copied out of the mmap buffers: distinct arrays that stay valid.
    assert stats["delivered"] + stats["discarded_at_stop"] == io.dequeued
    assert frames[0].image is not frames[-1].image and frames[0].image.flags.writeable


def test_format_preference(image):
    with V4L2Camera("/dev/video0", io=FakeV4L2IO(image, formats=("MJPG", "YUYV"))) as cam:
        assert cam.pixel_format == "YUYV"
    with V4L2Camera("/dev/video0", io=FakeV4L2IO(image)) as cam:
        assert cam.pixel_format == "RGB3"
    with pytest.raises(DriverError, match=r"pixel format RGB3 not offered \(device has MJPG\)"):
        V4L2Camera("/dev/video0", pixel_format="RGB3", io=FakeV4L2IO(image, formats=("MJPG",))
                   ).open()


def test_exposure_manual_and_read_back(image):
    io = FakeV4L2IO(image)
    with V4L2Camera("/dev/video0", io=io) as cam:
        # open() switched every automatic control off
        assert io.controls[v.CID_EXPOSURE_AUTO][4] == v.EXPOSURE_MANUAL
        assert io.controls[v.CID_AUTOGAIN][4] == 0
        assert io.controls[v.CID_AUTO_WHITE_BALANCE][4] == 0
        assert cam.exposure_s == pytest.approx(0.025)
        assert cam.set_exposure(0.0123) == pytest.approx(0.0123)
        assert io.controls[v.CID_EXPOSURE_ABSOLUTE][4] == 123
        assert cam.exposure_s == pytest.approx(0.0123)
        assert cam.set_gain(64) == 64
        frame = grab(cam, 1)[0]
        assert frame.exposure_s == pytest.approx(0.0123)
        with pytest.raises(DriverError, match=r"exposure 1 s outside the device's range "
                                              r"0.0003..0.2047 s"):
            cam.set_exposure(1.0)


def test_auto_control_that_stays_on_is_an_error(image):
    with pytest.raises(DriverError, match="v4l2:/dev/video0: device refuses to switch autogain"):
        V4L2Camera("/dev/video0", io=FakeV4L2IO(image, refuse_autogain=True)).open()


def test_frame_rate_and_size(image):
    with V4L2Camera("/dev/video0", io=FakeV4L2IO(image)) as cam:
        assert cam.set_frame_rate(60.0) == 60.0
        assert cam.set_frame_rate(50.0) == 60.0  # the device snaps to what it can do
        cam.set_size(320, 240)
        assert cam.size == (320, 240)
        assert grab(cam, 1)[0].image.shape == (240, 320, 3)
        with pytest.raises(DriverError, match="asked for image size 1600x1200, device gives"):
            cam.set_size(1600, 1200)
        assert cam.size == (320, 240)


def test_error_buffers_are_counted_and_skipped(image):
    io = FakeV4L2IO(image)
    io.error_frames = {2, 3}
    with V4L2Camera("/dev/video0", io=io) as cam:
        frames = grab(cam, 5)
        assert [f.index for f in frames] == [0, 1, 4, 5, 6]
        assert cam.stats()["failures"] == 2 and cam.stats()["missing_frames"] == 0


def test_undecodable_frames_are_counted_and_skipped(image):
    io = FakeV4L2IO(image, formats=("MJPG",))
    io.truncated_frames = {2}
    with V4L2Camera("/dev/video0", io=io) as cam:
        frames = grab(cam, 5)
        assert [f.index for f in frames] == [0, 1, 3, 4, 5]
        assert cam.stats()["bad_buffers"] == 1 and cam.stats()["failures"] == 0


def test_unplugged_mid_stream(image):
    io = FakeV4L2IO(image)
    cam = V4L2Camera("/dev/video0", io=io)
    cam.open()
    got = 0
    with pytest.raises(DeviceLostError) as info:
        for _ in cam.frames():
            got += 1
            if got == 3:
                io.unplug()
    assert str(info.value) == "v4l2:/dev/video0: device lost (dequeue: No such device)"
    cam.close()
    cam.close()
    assert not io.open_fds


def test_stop_from_another_thread(image):
    with V4L2Camera("/dev/video0", io=FakeV4L2IO(image)) as cam:
        timer = threading.Timer(0.2, cam.stop)
        timer.start()
        n = sum(1 for _ in cam.frames())
        timer.join()
        assert n > 1


def test_buffer_pool_holds_a_second_of_frames(image):
    io = FakeV4L2IO(image)
    with V4L2Camera("/dev/video0", io=io) as cam:
        assert cam.set_frame_rate(15.0) == 15.0
        grab(cam, 1)
        assert cam.stats()["buffers"] == 15
        cam.set_frame_rate(60.0)
        grab(cam, 1)
        assert cam.stats()["buffers"] == io.MAX_BUFFERS  # asked 60, the kernel gives 32
    # capped by memory: 640x480 RGB3 is 0.88 MiB a buffer
    with V4L2Camera("/dev/video0", io=FakeV4L2IO(image), max_buffer_mib=5) as cam:
        grab(cam, 1)
        assert cam.stats()["buffers"] == 5
    with V4L2Camera("/dev/video0", io=FakeV4L2IO(image), n_buffers=6) as cam:
        grab(cam, 1)
        assert cam.stats()["buffers"] == 6


def test_slow_consumer_does_not_starve_the_device(image):
    """A consumer that stalls (first-frame compilation, a slow disk) loses nothing.

    The acquisition thread keeps the buffers cycling; the copies wait for the
    consumer.  With a starved queue the device would skip frames (io.lost_frames).
    """
    io = FakeV4L2IO(image, formats=("YUYV",), sizes=((320, 240),))
    with V4L2Camera("/dev/video0", io=io, n_buffers=4) as cam:
        cam.set_frame_rate(60.0)
        frames = []
        for frame in cam.frames():
            frames.append(frame.index)
            if len(frames) in (1, 20):
                assert io.wait_dequeued(len(frames) + 45)  # 3/4 s of frames arrive meanwhile
            if len(frames) == 100:
                cam.stop()
        stats = cam.stats()
    assert frames == list(range(100))
    assert io.lost_frames == 0 and stats["missing_frames"] == 0
    assert stats["dropped_in_driver"] == 0 and stats["delivered"] == 100
    assert stats["delivered"] + stats["discarded_at_stop"] == io.dequeued


def test_consumer_far_behind_drops_the_oldest_and_counts(image):
    io = FakeV4L2IO(image, formats=("RGB3",), sizes=((320, 240),))
    frame_mib = 320 * 240 * 3 / 2**20
    with V4L2Camera("/dev/video0", io=io, max_pending_mib=3.5 * frame_mib) as cam:
        cam.set_frame_rate(60.0)
        indices = []
        for frame in cam.frames():
            indices.append(frame.index)
            if len(indices) == 1:
                assert io.wait_dequeued(30)  # far behind: 3 frames fit in the queue
            if frame.index >= 40:
                cam.stop()
        stats = cam.stats()
    dropped = stats["dropped_in_driver"]
    assert dropped >= 20
    # every gap in the indices is a counted drop; every frame is accounted for
    assert indices[-1] - indices[0] + 1 - len(indices) == dropped
    assert stats["delivered"] + dropped + stats["discarded_at_stop"] == io.dequeued
    assert io.lost_frames == 0 and stats["missing_frames"] == 0


def test_open_errors_are_one_line(image):
    io = FakeV4L2IO(image, denied={"/dev/video0"})
    with pytest.raises(DriverError, match=r"permission denied; add your user to the 'video'"):
        V4L2Camera("/dev/video0", io=io).open()
    with pytest.raises(DriverError, match="v4l2:/dev/video9: no such device"):
        V4L2Camera("/dev/video9", io=io).open()
    # The real I/O layer on a node that is not V4L2: the kernel answers ENOTTY.
    with pytest.raises(DriverError, match=r"^v4l2:/dev/null: not a V4L2 device"):
        V4L2Camera("/dev/null").open()


def test_list_devices(image):
    io = FakeV4L2IO(image, formats=("YUYV", "MJPG"))
    io.denied = {"/dev/video1"}
    found = list_v4l2_devices(io=io, paths=["/dev/video0", "/dev/video1"])
    assert found[0].card == "Fake webcam" and found[0].driver == "uvcvideo"
    assert found[0].formats == {"YUYV": [(640, 480), (320, 240)],
                                "MJPG": [(640, 480), (320, 240)]}
    assert found[1].path == "/dev/video1" and "permission denied" in found[1].problem
    assert not io.open_fds
