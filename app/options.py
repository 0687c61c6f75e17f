"""Command-line options and run set-up shared by the commands.

Output options and sinks (``replay``, ``capture``, ``demo``), pipeline options
(``replay``, ``capture``, ``batch``), projector screens (``project``,
``capture``, ``calibrate``) and image writing (``rig``, ``calibrate``).  Command
modules import from here, never from each other.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2

from lightflow.app.core.errors import ConfigError
from lightflow.app.core.rig import GAMMA_RANGE


def write_images(images: dict, out: Path) -> list[Path]:
    """Write ``name -> BGR image`` as ``out/<name>.png``; the paths written."""
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"{out}: cannot create the folder: {exc.strerror}") from None
    written = []
    for name, img in images.items():
        path = out / f"{name}.png"
        if not cv2.imwrite(str(path), img):
            raise ConfigError(f"{path}: cannot write the picture")
        written.append(path)
    return written


def parse_screens(text: str, projector_names: list[str]) -> list[int | str]:
    """Split ``--screens`` into one selector per projector (ints for digit strings)."""
    parts = [s.strip() for s in text.split(",")]
    if any(not s for s in parts) or len(parts) != len(projector_names):
        raise ConfigError(
            f"--screens: expected {len(projector_names)} comma-separated screen(s) for "
            f"projector(s) {', '.join(projector_names)}, got {text!r}"
        )
    return [int(s) if s.isdigit() else s for s in parts]


def add_output_options(p: argparse.ArgumentParser, rerun_required: bool = False) -> None:
    """``--rrd/--spawn/--serve``, ``--compress``, ``--export-depth``, ``--export-ply``."""
    g = p.add_mutually_exclusive_group(required=rerun_required)
    g.add_argument("--rrd", metavar="FILE", help="write a Rerun recording (open: rerun FILE)")
    g.add_argument("--spawn", action="store_true", help="show results in a new Rerun viewer")
    g.add_argument(
        "--serve", action="store_true",
        help="serve results on 127.0.0.1:9876 (view: rerun --connect rerun+http://127.0.0.1:9876/proxy)",
    )  # fmt: skip
    p.add_argument("--compress", action="store_true", help="log camera images to Rerun as JPEG")
    p.add_argument("--export-depth", metavar="DIR", help="write DIR/<frame>.npy depth maps (m)")
    p.add_argument(
        "--export-ply", metavar="DIR",
        help="write DIR/<frame>.ply point clouds (world axes, y up; see docs/formats.md)",
    )  # fmt: skip


#: the analysis grid strides the commands offer (those :class:`PipelineConfig` accepts)
STRIDES = (1, 2, 4, 8)


def add_pipeline_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--stride", type=int, choices=STRIDES, default=4,
        help="analysis grid stride in pixels (1 = finest, slowest; default 4; 8 takes about "
             "half the CPU of 4 for the same accuracy, but a few points less coverage, and "
             "as little as half on an object small in the image: a ball in a 640x480 view "
             "77 -> 40 %%)",
    )  # fmt: skip
    p.add_argument(
        "--smoothing", type=float, metavar="PX",
        help="sigma of the flow-ratio smoothing in camera pixels (default: the pipeline's)",
    )  # fmt: skip
    p.add_argument(
        "--static-depth", choices=("auto", "on", "off"), default="auto",
        help="single projector: also give depth where the lines stand still, from the ratio "
        "of the line intervals, which needs no motion ('auto', the default, is on for "
        "single-projector rigs and off for two projectors, whose depth is in the motion)",
    )  # fmt: skip
    p.add_argument(
        "--arc-recheck", choices=("on", "off"), default="off",
        help="with --arc-intervals on: where a ball's limb band had its arc placed at a "
        "neighbour's depth that the frame then does not measure at the band (by over 5 %%), "
        "place it again at the measured depth and read the flows again. 'off' (the "
        "default): on the development rigs' two balls 'on' gained up to 12 points of "
        "coverage, held out 0-3.5 points with more gross errors on some rigs, and it "
        "costs 15-30 ms per 1600x1200 frame of a ball or fan",
    )  # fmt: skip
    p.add_argument(
        "--whole-columns", choices=("on", "off"), default="on",
        help="the projected lines sit on whole projector columns (as `lightflow project` and "
        "`lightflow patterns` draw them), so their spacings are whole numbers of columns, "
        "not the pitch: take that out of every line interval ('on', the default); 'off' "
        "for patterns drawn at their exact, fractional centres",
    )  # fmt: skip
    p.add_argument(
        "--arc-intervals", choices=("on", "off"), default="on",
        help="two projectors: read each band's line interval from the circular arc through "
        "its line and its two neighbours, placed at the first pass's depth, instead of their "
        "mean spacing, which on a curved surface (a ball) is a few tenths of a per cent to "
        "over a per cent long and biases the depth ('on', the default); 'off' saves 1-5 ms "
        "per 1600x1200 frame where many intervals change (a steeply lit board)",
    )  # fmt: skip
    p.add_argument(
        "--triangulate", choices=("on", "off"), default="on",
        help="give each band the depth where its camera ray meets its line's plane, the line "
        "being the one the flows' depth names and both patterns' depths agree on (to about "
        "0.1 mm on rendered balls and fans, against 6-16 mm from the flows alone), and the "
        "moving pixels between such bands their depth ('on', the default); 'off' keeps the "
        "flows' depth everywhere",
    )  # fmt: skip
    p.add_argument(
        "--camera-gamma", metavar="G|auto",
        help="the camera's response, DN = full * (light / full) ** (1 / G): 1 for a linear "
        "camera, about 2.2 for a webcam or an sRGB image; every frame is linearised with it "
        "before the bands are measured; 'auto' measures it on a wall's lines that stand still "
        "between the first frames (default: the rig's camera.gamma, or 1; `lightflow rig "
        "blur` measures it on a still board, which is more reliable)",
    )  # fmt: skip


def pipeline_config(args: argparse.Namespace):
    """The :class:`PipelineConfig` the options ask for."""
    from lightflow.app.core.flow import FlowParams
    from lightflow.app.core.pipeline import PipelineConfig

    smoothing = getattr(args, "smoothing", None)
    flow = {"static_depth": getattr(args, "static_depth", "auto")}
    if smoothing is not None:
        if not smoothing >= 0:
            raise ConfigError(f"--smoothing: expected a non-negative number of pixels, "
                              f"got {smoothing}")  # fmt: skip
        flow["smoothing_px"] = smoothing
    gamma = getattr(args, "camera_gamma", None)
    if gamma not in (None, "auto"):
        lo, hi = GAMMA_RANGE
        try:
            gamma = float(gamma)
        except ValueError:
            gamma = float("nan")
        if not lo <= gamma <= hi:
            raise ConfigError(f"--camera-gamma: expected 'auto' or {lo:g} to {hi:g} (1: a "
                              f"linear camera), got {args.camera_gamma}")  # fmt: skip
    whole = getattr(args, "whole_columns", "on") == "on"
    arcs = getattr(args, "arc_intervals", "on") == "on"
    recheck = getattr(args, "arc_recheck", "off") == "on"
    tri = getattr(args, "triangulate", "on") == "on"
    return PipelineConfig(stride=args.stride, flow=FlowParams(**flow), camera_gamma=gamma,
                          whole_columns=whole, arc_intervals=arcs, arc_recheck=recheck,
                          triangulate=tri)  # fmt: skip


def make_pipeline(rig, args: argparse.Namespace):
    """The depth pipeline, showing progress while its LUT is built (first use of a rig)."""
    from lightflow.app.core.pipeline import DepthPipeline
    from lightflow.app.status import Progress

    return DepthPipeline(rig, pipeline_config(args), progress=Progress("building depth LUT"))


def build_sinks(args: argparse.Namespace, rig) -> list:
    """The sinks the output options ask for (on failure, those already open are closed)."""
    sinks: list = []
    try:
        if args.rrd or args.spawn or args.serve:
            from lightflow.app.sinks.rerun_sink import RerunSink

            mode = "rrd" if args.rrd else "spawn" if args.spawn else "serve"
            sinks.append(RerunSink(rig, mode, path=args.rrd, compress=args.compress))
        if args.export_depth:
            from lightflow.app.sinks.depth_export import DepthExportSink

            sinks.append(DepthExportSink(args.export_depth))
        if args.export_ply:
            from lightflow.app.sinks.ply import PlyExportSink

            sinks.append(PlyExportSink(args.export_ply, rig))
    except BaseException:
        close_all(sinks)
        raise
    return sinks


def close_all(sinks) -> None:
    """Close sinks that never reached a Runner (errors ignored: another one is on its way)."""
    for sink in sinks:
        try:
            sink.close()
        except Exception:  # noqa: BLE001, S110 - the original error is the one to report
            pass


def describe_outputs(sinks, out=None) -> None:
    out = out if out is not None else sys.stdout
    for sink in sinks:
        describe = getattr(sink, "describe", None)
        if describe is not None:
            print(describe(), file=out)


def check_rig_fits_recording(rig, rig_path, recording) -> None:
    """Refuse an override rig whose camera size differs from the recording's, before the
    (slow) LUT build rather than on every frame."""
    from lightflow.app.recording import read_recording

    embedded = read_recording(recording).rig.camera
    if (embedded.width, embedded.height) != (rig.camera.width, rig.camera.height):
        raise ConfigError(
            f"--rig {rig_path}: camera is {rig.camera.width}x{rig.camera.height}, but the "
            f"recording {recording} holds {embedded.width}x{embedded.height} frames"
        )

