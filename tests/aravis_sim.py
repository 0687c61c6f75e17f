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


class Simulator:
    """A GigE Vision simulator in a child process, on the loopback interface.

    Use as a context manager; :meth:`kill` simulates a camera that disappears.
    """

    def __init__(self, serial: str = "GV01") -> None:
        self.serial = serial
        self.proc: subprocess.Popen[str] | None = None

    def start(self) -> None:
        cmd = [sys.executable, __file__, "--interface", "lo", "--serial", self.serial]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
        # The child writes one line once its camera is serving (or fails and
        # exits); a watchdog bounds the wait instead of polling.
        watchdog = threading.Timer(READY_TIMEOUT_S, self.proc.kill)
        watchdog.start()
        try:
            line = self.proc.stdout.readline().strip()
        finally:
            watchdog.cancel()
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
    args = parser.parse_args()
    sys.exit(_serve(args.interface, args.serial))
