"""``lightflow devices``: the cameras and screens this machine offers, and access problems."""

from __future__ import annotations

import argparse
import glob
import os
from dataclasses import dataclass
from pathlib import Path

DESCRIPTION = """\
List what lightflow can capture from and project to:

  - GigE Vision and USB3 Vision cameras found by Aravis discovery
    (use them as aravis:<id> or aravis:<address>).  Discovery broadcasts
    on every network interface; --no-discovery skips it.
  - Video4Linux2 capture devices /dev/video* with their formats and sizes
    (use them as v4l2:/dev/videoN).
  - The screens of the X display ($DISPLAY), in the order --screens uses.

Device nodes the current user cannot open are reported with how to fix
that: install the udev rules shipped in udev/ (see udev/README.md) and add
the user to the 'video' (V4L2) or 'plugdev' (USB3 Vision) group."""

EPILOG = """\
examples:
  lightflow devices                     # cameras (Aravis discovery, V4L2), screens, permissions
  lightflow devices --no-discovery      # skip the GigE Vision broadcast"""


USB_SYSFS = "/sys/bus/usb/devices"
#: USB3 Vision: interface class Miscellaneous (0xEF), subclass 0x05, protocol 0x00
U3V_INTERFACE = ("ef", "05", "00")
UDEV_HINT = (
    "fix: sudo cp udev/*.rules /etc/udev/rules.d/ && sudo udevadm control --reload-rules "
    "&& sudo udevadm trigger; then sudo usermod -aG video,plugdev $USER and log in again"
)


#: printed when no camera of any kind was found: what to try next
NONE_FOUND_HINT = """\
Next steps:
  - USB3 Vision camera: install the udev rules (udev/README.md), join the
    'plugdev' group, log in again, then plug the camera in again.
  - GigE Vision camera: put this machine on the camera's subnet and let UDP
    port 3956 (GVCP) through the firewall; `arv-tool-0.8` lists what Aravis sees.
  - V4L2 camera (webcam): join the 'video' group; /dev/video* must exist.
  - No hardware at hand:
      lightflow demo                                  (a rendered moving scene)
      lightflow capture --camera synthetic:ball --rig two-projector
      lightflow capture --camera replay:REC           (a recording played as a camera)
      arv-fake-gv-camera-0.8 -i 127.0.0.1, then --camera aravis:127.0.0.1
                                                      (the Aravis GigE Vision simulator)"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "devices",
        help="list cameras (Aravis, V4L2) and screens, and check device permissions",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--no-discovery",
        action="store_true",
        help="skip Aravis discovery (it broadcasts GigE Vision packets on every interface)",
    )
    p.set_defaults(func=run)


@dataclass(frozen=True)
class UsbNode:
    """A USB3 Vision camera's device node and whether this user can open it."""

    node: str
    vendor: str
    product: str
    accessible: bool


def usb3vision_nodes(sysfs: str = USB_SYSFS, dev_root: str = "/dev/bus/usb") -> list[UsbNode]:
    """USB devices with a USB3 Vision interface, from sysfs (no USB traffic).

    Parameters
    ----------
    sysfs : str
        The USB devices folder of sysfs.
    dev_root : str
        Where the USB device nodes live.
    """
    found = {}
    for iface in sorted(glob.glob(os.path.join(sysfs, "*:*"))):
        try:
            cls = tuple(
                Path(iface, name).read_text().strip().lower()
                for name in ("bInterfaceClass", "bInterfaceSubClass", "bInterfaceProtocol")
            )
        except OSError:
            continue
        if cls != U3V_INTERFACE:
            continue
        device = Path(iface).resolve().parent
        try:
            bus, dev = (int(Path(device, n).read_text()) for n in ("busnum", "devnum"))
            vendor, product = (Path(device, n).read_text().strip()
                               for n in ("idVendor", "idProduct"))
        except (OSError, ValueError):
            continue
        node = os.path.join(dev_root, f"{bus:03d}", f"{dev:03d}")
        found[node] = UsbNode(node, vendor, product, os.access(node, os.R_OK | os.W_OK))
    return list(found.values())


def _aravis_lines(discover: bool) -> tuple[list[str], bool]:
    from lightflow.app.core.errors import DriverError

    if not discover:
        return ["  (discovery skipped)"], False
    try:
        from lightflow.drivers.aravis import list_aravis_devices

        devices = list_aravis_devices()
    except DriverError as exc:
        return [f"  not available: {exc}"], False
    if not devices:
        return ["  none found"], False
    return [
        f"  aravis:{d.id}  {d.vendor} {d.model}, serial {d.serial}, "
        f"{d.protocol} at {d.address or d.physical_id}"
        for d in devices
    ], True


def _v4l2_lines() -> tuple[list[str], bool]:
    from lightflow.drivers.v4l2 import list_v4l2_devices

    devices = list_v4l2_devices()
    if not devices:
        return ["  none found"], False
    lines, denied = [], False
    for d in devices:
        if d.problem:
            lines.append(f"  v4l2:{d.path}  cannot open: {d.problem}")
            denied |= "permission denied" in d.problem
            continue
        lines.append(f"  v4l2:{d.path}  {d.card} ({d.driver}, {d.bus_info})")
        for code, sizes in (d.formats or {}).items():
            listed = " ".join(f"{w}x{h}" for w, h in sizes[:8]) or "(sizes not listed)"
            more = f" (+{len(sizes) - 8} more)" if len(sizes) > 8 else ""
            lines.append(f"      {code}: {listed}{more}")
    return lines, denied


def _usb_lines() -> tuple[list[str], bool]:
    nodes = usb3vision_nodes()
    if not nodes:
        return ["  none found"], False
    lines = [
        f"  {n.node}  {n.vendor}:{n.product}  "
        + ("ok" if n.accessible else "permission denied (needs the udev rule, group plugdev)")
        for n in nodes
    ]
    return lines, not all(n.accessible for n in nodes)


def _screen_lines() -> list[str]:
    no_display = ["screens: no display (set DISPLAY)"]
    if not os.environ.get("DISPLAY"):
        return no_display
    try:
        from lightflow.drivers.projector import list_screens

        screens = list_screens()
    except Exception:  # noqa: BLE001 - any failure to reach X means "no display" here
        return no_display
    lines = [f"Screens (DISPLAY={os.environ['DISPLAY']}):"]
    lines += [f"  {s.index}: {s.name}  {s.width}x{s.height} at +{s.x}+{s.y}" for s in screens]
    return lines


def run(args: argparse.Namespace) -> int:
    print("Aravis cameras (GigE Vision, USB3 Vision):")
    aravis, aravis_found = _aravis_lines(not args.no_discovery)
    print("\n".join(aravis))
    print("USB3 Vision device nodes:")
    usb, usb_denied = _usb_lines()
    print("\n".join(usb))
    print("V4L2 devices:")
    v4l2, v4l2_denied = _v4l2_lines()
    print("\n".join(v4l2))
    print("\n".join(_screen_lines()))
    if usb_denied or v4l2_denied:
        print(UDEV_HINT)
    nodes_found = any(not line.startswith("  none found") for line in usb + v4l2)
    if not (aravis_found or nodes_found):
        print("No camera found." if not args.no_discovery
              else "No USB3 Vision or V4L2 camera found (GigE Vision discovery skipped).")
        print(NONE_FOUND_HINT)
    return 0
