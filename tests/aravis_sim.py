"""Start and stop the Aravis GigE Vision simulator for tests.

The simulator is Aravis's own ``ArvGvFakeCamera`` (the code behind the
``arv-fake-gv-camera-0.8`` program, which is not installed here because its
package pulls in GTK).  It runs in a child process, serves the real GigE Vision
control and stream protocols on the loopback interface, and is stopped by PID,
so killing it mid-stream looks to the driver exactly like a camera that loses
power.

Run as a program it is the simulator itself::

    python tests/aravis_sim.py --interface lo --serial GV01

It prints ``ready`` on stdout once the camera answers, and stops on SIGTERM.

With ``--frames-from REC`` (a lightflow recording) it streams that
recording's frames, one after the other and round again, instead of Aravis's
test pattern, converted to the pixel format the client chose (RGB8, Mono8 or
an 8-bit Bayer mosaic): the pipeline then sees real projected lines.

With ``--hold ADDRESS`` it is instead a second client that takes the camera's
control channel and keeps it (Aravis's heartbeat) until it is killed: a
crashed lightflow, once :meth:`Holder.kill` sends it SIGKILL.  It talks from
``127.0.0.2``, because the simulator tells clients apart by IP address only,
and every client on ``127.0.0.1`` would be the same controller to it.
"""

from __future__ import annotations

import argparse
import fcntl
import signal
import socket
import struct
import subprocess
import sys
import threading

SIM_ADDRESS = "127.0.0.1"
#: the other client's address (all of 127.0.0.0/8 is local to ``lo`` on Linux)
HOLDER_ADDRESS = "127.0.0.2"
READY_TIMEOUT_S = 10.0
SIOCGIFFLAGS = 0x8913
IFF_UP = 0x1


def private_netns_problem() -> str | None:
    """Return why this is not a private network namespace, or None if it is.

    Aravis discovery broadcasts on every interface; the tests must only ever
    see ``lo`` (``make test`` runs them under ``unshare --net``).
    """
    # Ask the kernel about *this* namespace (/sys/class/net shows the one
    # sysfs was mounted in, which unshare does not change).
    names = sorted(name for _, name in socket.if_nameindex())
    if names != ["lo"]:
        return (
            f"the Aravis tests must run in a private network namespace (only 'lo'), "
            f"found interfaces {names}; run: unshare --net sh -c "
            f"'ip link set lo up && exec .venv/bin/python -m pytest -q tests/...'"
        )
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        request = struct.pack("16sH14x", b"lo", 0)
        flags = struct.unpack("16sH14x", fcntl.ioctl(sock, SIOCGIFFLAGS, request))[1]
    if not flags & IFF_UP:
        return "loopback is down in this network namespace; run `ip link set lo up` first"
    return None



def start_child(cmd: list[str]) -> tuple[subprocess.Popen, str]:
    """Start ``cmd`` and read the one line it writes when ready (or failing).

    A watchdog kills a child that says nothing within ``READY_TIMEOUT_S``
    instead of polling it.
    """
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
    watchdog = threading.Timer(READY_TIMEOUT_S, proc.kill)
    watchdog.start()
    try:
        return proc, proc.stdout.readline().strip()
    finally:
        watchdog.cancel()

class Simulator:
    """A GigE Vision simulator in a child process, on the loopback interface.

    Use as a context manager; :meth:`kill` simulates a camera that disappears.
    """

    def __init__(self, serial: str = "GV01", frames_from: str | None = None) -> None:
        self.serial = serial
        self.frames_from = frames_from
        self.proc: subprocess.Popen[str] | None = None

    def start(self) -> None:
        cmd = [sys.executable, __file__, "--interface", "lo", "--serial", self.serial]
        if self.frames_from is not None:
            cmd += ["--frames-from", str(self.frames_from)]
        self.proc, line = start_child(cmd)
        if line != "ready":
            self.stop()
            raise RuntimeError(f"GigE Vision simulator did not start (said {line!r})")

    def kill(self) -> None:
        """Kill the simulator abruptly (SIGKILL), like pulling the camera's cable."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=10)

    def stop(self) -> None:
        """Stop the simulator by PID (SIGTERM, then SIGKILL if it does not exit)."""
        if self.proc is None:
            return
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5)
        self.proc.stdout.close()
        self.proc = None

    def __enter__(self) -> Simulator:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


class Holder:
    """Another client in a child process that holds the simulator's control channel.

    Use as a context manager; :meth:`kill` (SIGKILL) leaves the camera
    controlled by a dead client until its heartbeat times out.
    """

    def __init__(self, device: str = SIM_ADDRESS) -> None:
        self.device = device
        self.proc: subprocess.Popen[str] | None = None

    def start(self) -> None:
        cmd = [sys.executable, __file__, "--hold", self.device, "--source", HOLDER_ADDRESS]
        self.proc, line = start_child(cmd)
        if line != "holding":
            self.kill()
            raise RuntimeError(f"the second client did not take control (said {line!r})")

    def kill(self) -> None:
        """SIGKILL: the client dies without releasing control, as after kill -9."""
        if self.proc is not None:
            if self.proc.poll() is None:
                self.proc.kill()
            self.proc.wait(timeout=10)
            self.proc.stdout.close()
            self.proc = None

    def __enter__(self) -> Holder:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.kill()


def _hold(device: str, source: str) -> int:
    import gi

    gi.require_version("Aravis", "0.8")
    from gi.repository import Aravis, Gio

    # Opening a GvDevice takes control and starts its heartbeat thread.
    dev = Aravis.GvDevice.new(Gio.InetAddress.new_from_string(source),
                              Gio.InetAddress.new_from_string(device))
    if not dev.is_controller():
        print("not controller", flush=True)
        return 1
    print("holding", flush=True)
    threading.Event().wait()  # until killed
    return 0


#: GenICam pixel format codes the recorded frames are converted to, and the Bayer
#: mosaics' colour at (row 0, column 0), (0, 1), (1, 0), (1, 1) (0 R, 1 G, 2 B)
PIXEL_RGB8 = 0x02180014
PIXEL_MONO8 = 0x01080001
BAYER8 = {0x01080009: (0, 1, 1, 2), 0x01080008: (1, 0, 2, 1), 0x0108000A: (1, 2, 0, 1),
          0x0108000B: (2, 1, 1, 0)}  # RG, GR, GB, BG


class RecordedFrames:
    """The fake camera's fill pattern: a recording's frames, in a loop.

    Aravis calls :meth:`fill` on its streaming thread with each buffer it is about
    to send; the frame's pixels, converted to the pixel format the client chose,
    are copied into the buffer's memory.  Everything goes through libaravis by
    ctypes: PyGObject frees the callback of ``set_fill_pattern`` as soon as that
    call returns (its scope is "call"), and the next frame then segfaults; and it
    hands out only a copy of a buffer's data.
    """

    def __init__(self, rec: str) -> None:
        import ctypes

        import numpy as np

        from lightflow.app.recording import load_frame, read_recording

        recording = read_recording(rec)
        self.images = [np.ascontiguousarray(load_frame(recording, i))
                       for i in range(len(recording.frames))]  # fmt: skip
        self.sent = 0
        self.converted: dict[tuple[int, int, int], list[bytes]] = {}
        lib = ctypes.CDLL("libaravis-0.8.so.0")
        lib.arv_buffer_get_data.restype = ctypes.c_void_p
        lib.arv_buffer_get_data.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_size_t)]
        for name in ("arv_buffer_get_image_width", "arv_buffer_get_image_height"):
            getattr(lib, name).restype = ctypes.c_int
            getattr(lib, name).argtypes = [ctypes.c_void_p]
        lib.arv_fake_camera_set_fill_pattern.restype = None
        callback_type = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint32,
                                         ctypes.c_uint32, ctypes.c_uint32)  # fmt: skip
        lib.arv_fake_camera_set_fill_pattern.argtypes = [ctypes.c_void_p, callback_type,
                                                         ctypes.c_void_p]  # fmt: skip
        self._lib, self._ctypes = lib, ctypes
        self._callback = callback_type(self.fill)  # kept: libaravis holds only its address

    def install(self, fake_camera) -> None:
        """Make ``fake_camera`` (an ``Aravis.FakeCamera``) send these frames."""
        ctypes = self._ctypes
        pointer = ctypes.pythonapi.PyCapsule_GetPointer
        pointer.restype = ctypes.c_void_p
        pointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
        self._lib.arv_fake_camera_set_fill_pattern(
            pointer(fake_camera.__gpointer__, None), self._callback, None
        )

    def frames(self, width: int, height: int, pixel_format: int) -> list[bytes]:
        """The recording's frames as ``width`` x ``height`` buffers of ``pixel_format``."""
        import cv2  # only here: the plain simulator starts without OpenCV and NumPy
        import numpy as np

        key = (width, height, pixel_format)
        if key not in self.converted:
            out = []
            for img in self.images:
                if img.shape[:2] != (height, width):
                    img = cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)
                if pixel_format == PIXEL_MONO8:
                    img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
                elif pixel_format in BAYER8:
                    mosaic = np.empty((height, width), np.uint8)
                    for k, c in enumerate(BAYER8[pixel_format]):
                        mosaic[k // 2 :: 2, k % 2 :: 2] = img[k // 2 :: 2, k % 2 :: 2, c]
                    img = mosaic
                elif pixel_format != PIXEL_RGB8:
                    # a black frame, said once: an exception here would only be printed
                    print(f"--frames-from: pixel format {pixel_format:#010x} is not converted "
                          "(RGB8, Mono8 and 8-bit Bayer are): black frames", file=sys.stderr)
                    out = [bytes(width * height)] * len(self.images)
                    break
                out.append(np.ascontiguousarray(img).tobytes())
            self.converted[key] = out
        return self.converted[key]

    def fill(self, buffer, _data, _exposure_us, _gain, pixel_format) -> None:
        lib, ctypes = self._lib, self._ctypes
        width = lib.arv_buffer_get_image_width(buffer)
        height = lib.arv_buffer_get_image_height(buffer)
        data = self.frames(width, height, int(pixel_format))[self.sent % len(self.images)]
        self.sent += 1
        # the buffer holds the payload of this size and format; its received size is
        # still 0 here (set once the pattern is filled)
        address = lib.arv_buffer_get_data(buffer, None)
        ctypes.memmove(address, data, len(data))


def _serve(interface: str, serial: str, frames_from: str | None = None) -> int:
    import gi

    gi.require_version("Aravis", "0.8")
    from gi.repository import Aravis

    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    camera = Aravis.GvFakeCamera.new(interface, serial)
    if not camera.is_running():
        print("failed", flush=True)
        return 1
    if frames_from is not None:
        pattern = RecordedFrames(frames_from)
        pattern.install(camera.get_fake_camera())
    print("ready", flush=True)
    done.wait()
    del camera
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--interface", default="lo")
    parser.add_argument("--serial", default="GV01")
    parser.add_argument("--hold", metavar="ADDRESS", help="be a client holding this camera")
    parser.add_argument("--source", default=HOLDER_ADDRESS, help="the holding client's address")
    parser.add_argument("--frames-from", metavar="REC", help="stream this recording's frames")
    args = parser.parse_args()
    if args.hold:
        sys.exit(_hold(args.hold, args.source))
    sys.exit(_serve(args.interface, args.serial, args.frames_from))
