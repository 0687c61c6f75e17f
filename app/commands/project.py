"""``lightflow project``: show each projector's line pattern on its screen."""

from __future__ import annotations

import argparse
import signal
import sys
import threading

from lightflow.app.options import parse_screens

HELP = "show each projector's pattern fullscreen on its screen until Esc or Ctrl-C"

DESCRIPTION = """\
Show each projector's line pattern, 1:1 and unscaled, in a borderless
fullscreen window on the screen (X RandR output) that drives that projector.
A single projector shows both of its patterns in one image.

The window is placed exactly on the screen and its real position is checked;
a screen whose size differs from the projector's resolution is refused unless
--allow-size-mismatch is given (the image is then drawn at the top-left, black
elsewhere).  Runs until Ctrl-C, Esc in a window, or a window is closed."""

EPILOG = """\
screens are numbered from 0 in the order `lightflow devices` lists them;
names are RandR output names such as HDMI-1.  Example:
  lightflow project rig.json --screens 1,2
  lightflow project rig.json --screens HDMI-1,DP-2 --display :0"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "project",
        help=HELP,
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("rig", metavar="RIG", help="rig file (rig.json) whose patterns are shown")
    p.add_argument(
        "--screens",
        required=True,
        metavar="S1[,S2]",
        help="comma-separated screen index or name for each projector, in the rig's "
        "projector order",
    )
    p.add_argument("--display", metavar=":N", help="X display (default: $DISPLAY)")
    p.add_argument(
        "--allow-size-mismatch",
        action="store_true",
        help="accept a screen larger than the projector image (drawn 1:1 at the top-left)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from lightflow.app.core.patterns import pattern_image
    from lightflow.app.core.rig import resolve_rig
    from lightflow.drivers.projector import ProjectorWindows

    rig = resolve_rig(args.rig)
    names = [p.name for p in rig.projectors]
    selectors = parse_screens(args.screens, names)
    out = ProjectorWindows(
        [(p.name, s, pattern_image(p)) for p, s in zip(rig.projectors, selectors, strict=True)],
        display=args.display,
        allow_size_mismatch=args.allow_size_mismatch,
    )
    stop = threading.Event()
    interrupted = threading.Event()

    def on_ctrl_c(signum, frame) -> None:
        # an Event, not KeyboardInterrupt: the pyglet loop wakes on `stop` (its watcher
        # thread), and a Ctrl-C arriving outside the loop still ends it cleanly
        interrupted.set()
        stop.set()

    previous = signal.signal(signal.SIGINT, on_ctrl_c)
    try:
        with out:
            for name, screen in out.placements:
                print(f"projector {name} -> {screen.describe()}")
            print("showing; press Esc in a window or Ctrl-C here to stop", flush=True)
            if not interrupted.is_set():
                out.run(stop)
    finally:
        signal.signal(signal.SIGINT, previous)
    if interrupted.is_set():
        print("stopped", file=sys.stderr)
    return 0
