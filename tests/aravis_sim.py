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

    def __init__(self, serial: str = "GV01") -> None:
        self.serial = serial
        self.proc: subprocess.Popen[str] | None = None

    def start(self) -> None:
        cmd = [sys.executable, __file__, "--interface", "lo", "--serial", self.serial]
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


def _serve(interface: str, serial: str) -> int:
    import gi

    gi.require_version("Aravis", "0.8")
    from gi.repository import Aravis

    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    camera = Aravis.GvFakeCamera.new(interface, serial)
    if not camera.is_running():
        print("failed", flush=True)
        return 1
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
    args = parser.parse_args()
    if args.hold:
        sys.exit(_hold(args.hold, args.source))
    sys.exit(_serve(args.interface, args.serial))
