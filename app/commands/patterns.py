"""``lightflow patterns RIG --out DIR``: write each projector's pattern image as a PNG."""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2

from lightflow.app.core.errors import ConfigError
from lightflow.app.core.patterns import line_centres, pattern_image
from lightflow.app.core.rig import resolve_rig

DESCRIPTION = """\
Write the image each projector of a rig shows, at the projector's resolution,
as DIR/<projector name>.png (RGB, 8 bits: each pattern's lines at 255 in its
colour channel, black elsewhere).  Use it to display the patterns with another
program or to look at them; `lightflow project` shows them directly."""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "patterns",
        help="write each projector's pattern image as a PNG",
        description=DESCRIPTION,
        epilog="example:\n  lightflow patterns rig.json --out patterns/",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("rig", metavar="RIG", help="rig file (rig.json)")
    p.add_argument(
        "--out", required=True, metavar="DIR", help="folder for the PNGs (created if needed)"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    rig = resolve_rig(args.rig)
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"{out}: cannot create the folder: {exc.strerror}") from None
    for proj in rig.projectors:
        path = out / f"{proj.name}.png"
        # OpenCV writes BGR: flip the RGB pattern image so that red stays red
        if not cv2.imwrite(str(path), pattern_image(proj)[..., ::-1]):
            raise ConfigError(f"{path}: cannot write the pattern image")
        what = ", ".join(
            f"{pat.channel} {pat.kind} ({len(line_centres(pat, proj.width))} lines)"
            for pat in proj.patterns
        )
        print(f"wrote {path} ({proj.width}x{proj.height}: {what})")
    return 0
