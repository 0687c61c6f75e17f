"""``lightflow rig check RIG``: can this rig measure depth, and how well?

``lightflow rig blur REC... --out RIG``: measure each pattern's blur on still lines.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from lightflow.app.core.depth_model import DepthRange
from lightflow.app.core.errors import ConfigError
from lightflow.app.core.rig import resolve_rig
from lightflow.app.options import write_images
from lightflow.app.rigcheck import BAND_PX, MAX_ERROR_M, RigReport, check_rig

DESCRIPTION = f"""\
Check a rig file before scanning with it: is the log flow ratio h(z) steep and
monotonic (invertible) where the projectors light the scene, and what depth
error should you expect?

At each working depth (a flat surface facing the camera) the check reports,
on a coarse grid of camera pixels: where every projector lights the surface
(the overlap), where h(z) is flat (expected error above {1000 * MAX_ERROR_M:g} mm) or not
invertible over the depth range, the median slope |dh/dz| and the median
expected depth error for 1/4 px of error in the band length (assumed
{BAND_PX:g} px) and in the apparent line interval, as in the paper's precision
analysis.  Plain-words warnings follow, with what to move.

Pictures of these maps (slope, expected error, usable pixels, overlap, one set
per working depth) are written as PNGs only when --out DIR is given.

Exit status: 0 when the rig can measure depth (possibly with warnings), 2 when
it cannot (for example two parallel projectors side by side: h(z) is then
constant) or the rig file is invalid; the reason is printed on one line."""

EPILOG = """\
examples:
  lightflow rig check rig.json
  lightflow rig check rig.json --out rigcheck/ --depths 0.4 0.6 0.8"""


BLUR_DESCRIPTION = """\
Measure the camera's response curve and how blurred each pattern's lines are
in the camera, once per rig, and write both into the rig file (camera.gamma and
each pattern's "blur", with its "crosstalk").  Fast objects (a fan at 1 ms, a ball at 5 ms) move
their lines less than the lines' own width; their sweep then shows only in the
edges of the band, and reading it needs the blur.
Without this measurement the pipeline fits the blur on the moving bands of the
first frames of every run, which is noisier and biased on short bands.

Record still surfaces lit by the patterns (a board held still, or a wall), at
two or three distances across the working range: the camera's part of the
blur is fixed in camera pixels, the projector's defocus in projector pixels,
and the distances tell them apart.  Any exposure will do.

The response comes first: a still line's ramp gives its blur, its known width
and that blur give its width at half height, and a camera that is not linear
(a webcam, gamma about 2.2) reads every line wider; the gamma that makes them
agree is written as camera.gamma (1: linear), and every frame of every run is
linearised with it.  Prints the gamma, then per pattern the two parts of the
blur, the blur at a few magnifications and how many line measurements were
used.  Exit status 2 with one line when a recording shows too few still lines.

The still lines also give the colour crosstalk: the share of one pattern's
light that the other pattern's camera channel sees (each pattern's
"crosstalk").  Every frame has it subtracted.  Without it the pipeline
estimates it on the frames, which needs clean gaps between bands; long sweeps
leave too few, and then one pattern's lines show inside the other's bands."""

BLUR_EPILOG = """\
examples:
  lightflow capture --camera aravis:CAM --rig rig.json --record still-55cm --frames 1
  (move the board, repeat at 75 cm and 1 m)
  lightflow rig blur still-55cm still-75cm still-1m --out rig-blur.json
  lightflow simulate --scene board-steps --fps 1 --frames 3 --out steps
  lightflow rig blur steps --out rig-blur.json"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "rig",
        help="inspect a rig file (`lightflow rig check RIG`)",
        description="Inspect a rig file.",
    )
    sub = p.add_subparsers(dest="rig_command", metavar="SUBCOMMAND")
    sub.required = True
    c = sub.add_parser(
        "check",
        help="check that the rig can measure depth and estimate its depth error",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    c.add_argument("rig", metavar="RIG", help="rig file (rig.json)")
    c.add_argument(
        "--out",
        metavar="DIR",
        help="write the maps as PNG pictures into DIR (created if needed)",
    )
    c.add_argument(
        "--depths",
        metavar="Z",
        type=float,
        nargs="+",
        default=[0.5, 0.75, 1.0],
        help="working depths in metres to check at (default: 0.5 0.75 1.0)",
    )
    c.add_argument(
        "--near", type=float, default=DepthRange.near, metavar="M",
        help="near end of the depth range h(z) is inverted over (default: %(default)g m)",
    )  # fmt: skip
    c.add_argument(
        "--far", type=float, default=DepthRange.far, metavar="M",
        help="far end of the depth range (default: %(default)g m)",
    )  # fmt: skip
    c.add_argument(
        "--stride", type=int, default=8, metavar="PX",
        help="check every PX-th camera row and column (default: %(default)s)",
    )  # fmt: skip
    c.set_defaults(func=run)
    b = sub.add_parser(
        "blur",
        help="measure the camera's response and the blur of each pattern's lines on "
        "recordings of still surfaces",
        description=BLUR_DESCRIPTION,
        epilog=BLUR_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    b.add_argument("recordings", metavar="REC", nargs="+",
                   help="recording folders of still surfaces (lines that do not move)")
    b.add_argument("--rig", metavar="RIG",
                   help="rig file or example rig name (default: the rig the recording embeds)")
    b.add_argument("--out", metavar="RIG_OUT", required=True,
                   help="where to write the rig with the measured blur (rig.json)")
    b.set_defaults(func=run_blur)


def report_lines(report: RigReport) -> list[str]:
    """The check's numbers as a table whose rows say in words what each symbol means."""
    stats = report.stats
    lit = "lit by the projector" if report.single_projector else "lit by both projectors"

    def row(name: str, values) -> str:
        return f"  {name:<42}" + "".join(f"{v:>9}" for v in values)

    def pct(x: float) -> str:
        return f"{100 * x:.0f} %"

    def num(x: float, fmt: str) -> str:
        return "-" if not math.isfinite(x) else format(x, fmt)

    lines = [
        report.description,
        row("working depth z", [f"{st.z:.2f} m" for st in stats]),
        row(lit, [pct(st.lit) for st in stats]),
        row("usable: depth can be measured", [pct(st.usable) for st in stats]),
        row("flat h(z): too little change with depth", [pct(st.flat) for st in stats]),
        row("h(z) not invertible: depth ambiguous", [pct(st.not_invertible) for st in stats]),
        row("steepness |dh/dz| (1/m), median", [num(st.median_slope, ".2f") for st in stats]),
        row("expected depth error (mm), median",
            [num(st.median_error_mm, ".0f") for st in stats]),
    ]  # fmt: skip
    n_patterns = len(stats[0].median_interval_px) if stats else 0
    for i in range(n_patterns):
        values = [num(st.median_interval_px[i], ".1f") for st in stats]
        lines.append(row(f"line spacing B{i + 1} in the image (px), median", values))
    lines += [
        f"usable on {pct(report.coverage)} of the image, {lit} on {pct(report.overlap)} "
        "(means over the working depths)",
        "h(z) is the log ratio of the two light flows a surface at depth z gives;",
        "  the steeper it is (larger |dh/dz|), the finer the depth.",
        f"The expected depth error assumes 1/4 px of error in {BAND_PX:g} px long bands",
        "  and in the line spacings B.",
        "verdict: " + ("usable" if report.usable else f"degenerate: {report.problem}"),
    ]
    return lines


def run_blur(args: argparse.Namespace) -> int:
    from lightflow.app.blurcal import MIN_MAGNIFICATION_SPAN, calibrate_optics
    from lightflow.app.core.rig import save_rig
    from lightflow.app.recording import read_recording, recording_frames
    from lightflow.app.status import crosstalk_shares

    rig = resolve_rig(args.rig) if args.rig else None
    recs = [read_recording(path, rig) for path in args.recordings]
    rig = rig or recs[0].rig
    for path, rec in zip(args.recordings, recs, strict=True):
        if rec.rig.geometry_digest() != rig.geometry_digest():
            raise ConfigError(f"{path}: its rig differs from {recs[0].rig.source}: give --rig")
    frames = [frame for rec in recs for frame in recording_frames(rec)]
    # measured afresh: a crosstalk the rig file had is kept only where none was measured
    out, response, blurs = calibrate_optics(rig.with_crosstalk([None, None]), frames)
    if response is None:
        print(f"camera response: not measured (too few still lines); kept the rig's gamma "
              f"{rig.camera.gamma:g}")  # fmt: skip
    else:
        kind = ("linear" if response.gamma == 1.0
                else "not linear: every frame will be linearised with it")
        print(f"camera response: gamma {response.gamma:g} ({kind}; measured "
              f"{response.measured:.3f} on {response.lines} still line measurements, which "
              f"read {response.excess_linear_px:+.2f} px wide at half height if taken as linear)")
    for i, ((proj, pat), pb) in enumerate(zip(rig.patterns, blurs, strict=True), 1):
        lo, hi = pb.magnification
        print(f"pattern {i} ({pat.channel}, projector {proj.name}): blur sigma^2 = "
              f"{pb.camera_px2:.3f} px^2 (camera) + {pb.projector_px2:.3f} x m^2 (projector "
              f"defocus); sigma {pb.sigma_px(lo):.2f} px at m = {lo:.2f}, {pb.sigma_px(hi):.2f} px "
              f"at m = {hi:.2f}; {pb.lines} line measurements")  # fmt: skip
        if hi < MIN_MAGNIFICATION_SPAN * lo:
            print(f"WARNING pattern {i}: all lines were seen at about one magnification "
                  f"({lo:.2f}-{hi:.2f}): record still surfaces at other distances too, "
                  f"or the blur away from this one is a guess")  # fmt: skip
    measured = out.crosstalk
    if measured is None and rig.crosstalk is not None:
        out = out.with_crosstalk(rig.crosstalk)
        print("colour crosstalk: not measured (too few clean gaps between still lines); "
              "kept the rig file's")  # fmt: skip
    elif measured is None:
        print("colour crosstalk: not measured (too few clean gaps between still lines); "
              "the pipeline will estimate it on the frames")  # fmt: skip
    else:
        print(f"colour crosstalk: {crosstalk_shares(rig, measured)} (subtracted from every "
              f"frame)")  # fmt: skip
    save_rig(out, args.out)
    print(f"wrote {args.out}: the rig with the camera's response and each pattern's "
          f"measured blur and crosstalk")  # fmt: skip
    return 0


def run(args: argparse.Namespace) -> int:
    rig = resolve_rig(args.rig)
    if args.stride < 1:
        raise ConfigError(f"--stride: expected an integer >= 1, got {args.stride}")
    report = check_rig(rig, args.depths, DepthRange(args.near, args.far), args.stride)
    for line in report_lines(report):
        print(line)
    for warning in report.warnings:
        print(f"WARNING {warning}")
    if args.out:
        paths = write_images(report.images, Path(args.out))
        print(f"wrote {len(paths)} pictures to {args.out}: " + ", ".join(p.name for p in paths))
    else:
        print("(pictures of these maps: add --out DIR)")
    if report.problem:
        raise ConfigError(f"{args.rig}: {report.problem}")
    return 0
