"""Start and stop private X servers for tests (Xvfb, Xorg with the dummy driver).

The server picks a free display number itself and reports it through
``-displayfd`` once it accepts connections, so there is no guessing of free
numbers and no polling.  Servers listen only on their unix socket
(``-nolisten tcp``), which also works inside a private network namespace.
Each server is stopped by its PID.
"""

from __future__ import annotations

import os
import select
import shutil
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest

DATA = Path(__file__).parent / "data"
DUMMY_CONF = DATA / "xorg-dummy-2head.conf"
START_TIMEOUT_S = 20.0


@dataclass
class XServer:
    """A running X server: its display name (``":N"``), process and log."""

    display: str
    proc: subprocess.Popen
    log: Path
    extra: dict = field(default_factory=dict)

    @property
    def env(self) -> dict[str, str]:
        """The environment with ``DISPLAY`` pointing at this server."""
        env = dict(os.environ)
        env["DISPLAY"] = self.display
        return env

    def xrandr(self, *args: str) -> str:
        """Run ``xrandr`` against this server; raise with its output on failure."""
        res = subprocess.run(
            ["xrandr", *args], env=self.env, capture_output=True, text=True, timeout=20
        )
        if res.returncode != 0:
            raise RuntimeError(f"xrandr {' '.join(args)} failed: {res.stderr.strip()}")
        return res.stdout

    def stop(self) -> None:
        """Terminate the server by PID and reap it."""
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)


def start_server(argv: list[str], log: Path) -> XServer:
    """Start an X server command (without a display number) and wait until it is ready.

    Parameters
    ----------
    argv : list of str
        The server command, e.g. ``["Xvfb", "-screen", "0", "1280x800x24"]``;
        ``-displayfd`` and ``-nolisten tcp`` are added.
    log : pathlib.Path
        Where the server's stdout and stderr go.
    """
    if shutil.which(argv[0]) is None:
        pytest.skip(f"{argv[0]} is not installed")
    rfd, wfd = os.pipe()
    with open(log, "wb") as out:
        proc = subprocess.Popen(
            [*argv, "-nolisten", "tcp", "-displayfd", str(wfd)],
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=subprocess.STDOUT,
            pass_fds=(wfd,),
            start_new_session=True,  # a Ctrl-C of the test run does not hit it first
        )
    os.close(wfd)
    try:
        number = b""
        deadline = time.monotonic() + START_TIMEOUT_S
        while not number.endswith(b"\n"):
            left = deadline - time.monotonic()
            ready, _, _ = select.select([rfd], [], [], max(left, 0))
            chunk = os.read(rfd, 16) if ready else b""
            if not chunk:  # timeout, or the server exited and closed the pipe
                break
            number += chunk
    finally:
        os.close(rfd)
    if not number.strip().isdigit():
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=10)
        tail = log.read_text(errors="replace")[-2000:]
        raise RuntimeError(f"{argv[0]} did not start (exit {proc.returncode}):\n{tail}")
    return XServer(f":{number.decode().strip()}", proc, log)


def start_xvfb(tmp: Path, width: int = 1280, height: int = 800) -> XServer:
    """One-screen Xvfb of ``width`` x ``height`` at 24 bit."""
    return start_server(["Xvfb", "-screen", "0", f"{width}x{height}x24"], tmp / "xvfb.log")


def start_xorg_two_heads(tmp: Path, width: int = 1280, height: int = 800) -> XServer:
    """Xorg with the dummy driver and two RandR outputs DUMMY0, DUMMY1 side by side.

    Each head gets the mode ``width`` x ``height`` (added with ``--newmode`` if
    the server does not list it); the desktop is exactly both heads.
    """
    srv = start_server(
        [
            "Xorg", "-noreset", "-config", str(DUMMY_CONF.resolve()),
            "-logfile", str(tmp / "xorg.log"),
        ],
        tmp / "xorg.out",
    )
    try:
        mode = f"{width}x{height}"
        listing = srv.xrandr()
        if f"   {mode} " not in listing:
            # CVT-like timing; the dummy driver accepts any sane modeline
            srv.xrandr("--newmode", mode, "68.00", str(width), str(width + 48),
                       str(width + 80), str(width + 160), str(height), str(height + 3),
                       str(height + 9), str(height + 23), "+hsync", "-vsync")
            srv.xrandr("--addmode", "DUMMY0", mode)
        srv.xrandr("--addmode", "DUMMY1", mode)
        srv.xrandr(
            "--output", "DUMMY0", "--mode", mode, "--pos", "0x0",
            "--output", "DUMMY1", "--mode", mode, "--right-of", "DUMMY0",
            "--fb", f"{2 * width}x{height}",
        )
    except BaseException:
        srv.stop()
        raise
    return srv
