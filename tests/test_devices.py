"""``lightflow devices`` with the GigE Vision simulator running (private network namespace)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from aravis_sim import Simulator, private_netns_problem

from lightflow.app.cli import main
from lightflow.app.commands.devices import usb3vision_nodes


@pytest.fixture
def sim():
    problem = private_netns_problem()
    if problem:
        pytest.fail(problem)
    with Simulator(serial="DEV01") as simulator:
        yield simulator


@pytest.mark.aravis
def test_devices_lists_simulator(sim, capsys, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    assert main(["devices"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == "Aravis cameras (GigE Vision, USB3 Vision):"
    camera = [line for line in out if "DEV01" in line]
    assert len(camera) == 1
    assert camera[0].startswith("  aravis:")
    assert "Aravis Fake, serial DEV01, GigEVision at 127.0.0.1" in camera[0]
    # No V4L2 node can exist on this kernel; no X display was given.
    assert out[out.index("V4L2 devices:") + 1] == "  none found"
    assert out[-1] == "screens: no display (set DISPLAY)"  # a camera: no "next steps"


def test_devices_without_discovery(capsys, monkeypatch):
    monkeypatch.setenv("DISPLAY", ":987")  # no such server
    assert main(["devices", "--no-discovery"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[1] == "  (discovery skipped)"
    assert "screens: no display (set DISPLAY)" in out
    # nothing found: what to try next, down to the cameras that need no hardware
    hint = out[out.index("screens: no display (set DISPLAY)") + 1:]
    assert hint[0] == "No USB3 Vision or V4L2 camera found (GigE Vision discovery skipped)."
    text = "\n".join(hint)
    for step in ("udev/README.md", "plugdev", "'video' group", "lightflow demo",
                 "synthetic:ball", "replay:REC", "aravis:127.0.0.1"):
        assert step in text, step


def test_help_explains(capsys):
    with pytest.raises(SystemExit) as info:
        main(["devices", "--help"])
    assert info.value.code == 0
    text = capsys.readouterr().out
    assert "aravis:<id>" in text and "v4l2:/dev/videoN" in text and "udev/README.md" in text


def _usb_device(root: Path, name: str, bus: int, dev: int, ifaces: list[tuple[str, str, str]]):
    """A sysfs-shaped tree: the device folder with busnum/devnum and interface folders."""
    device = root / "devices" / name
    device.mkdir(parents=True)
    for key, value in (("busnum", bus), ("devnum", dev), ("idVendor", "1ab2"),
                       ("idProduct", "0001")):
        (device / key).write_text(f"{value}\n")
    for i, (cls, sub, proto) in enumerate(ifaces):
        iface = device / f"{name}:1.{i}"
        iface.mkdir()
        for key, value in (("bInterfaceClass", cls), ("bInterfaceSubClass", sub),
                           ("bInterfaceProtocol", proto)):
            (iface / key).write_text(f"{value}\n")
        (root / "bus").mkdir(exist_ok=True)
        (root / "bus" / iface.name).symlink_to(iface)


def test_usb3vision_nodes_from_sysfs(tmp_path):
    _usb_device(tmp_path, "2-1", 2, 5, [("ef", "05", "00"), ("ef", "05", "01")])
    _usb_device(tmp_path, "1-3", 1, 7, [("0e", "01", "00")])  # a UVC webcam: not U3V
    dev_root = tmp_path / "dev"
    (dev_root / "002").mkdir(parents=True)
    (dev_root / "002" / "005").write_text("")
    nodes = usb3vision_nodes(str(tmp_path / "bus"), str(dev_root))
    assert [(n.node, n.vendor, n.accessible) for n in nodes] == [
        (str(dev_root / "002" / "005"), "1ab2", True)]
    (dev_root / "002" / "005").chmod(0)
    nodes = usb3vision_nodes(str(tmp_path / "bus"), str(dev_root))
    # root can open anything; everyone else is told to fix the permissions
    assert nodes[0].accessible == (os.geteuid() == 0)


@pytest.mark.xserver
def test_devices_lists_screens(tmp_path, capsys, monkeypatch):
    from xserver import start_xvfb

    server = start_xvfb(tmp_path, 1280, 800)
    try:
        monkeypatch.setenv("DISPLAY", server.display)
        assert main(["devices", "--no-discovery"]) == 0
    finally:
        server.stop()
    out = capsys.readouterr().out.splitlines()
    i = out.index(f"Screens (DISPLAY={server.display}):")
    assert out[i + 1].startswith("  0: ") and out[i + 1].endswith("1280x800 at +0+0")
