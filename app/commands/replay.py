"""``lightflow replay``: reconstruct depth from a recording, losing no frame.

Also home of the output options shared by ``capture`` and ``demo``
(:func:`add_output_options`, :func:`build_sinks`, :func:`pipeline_config`).
"""

from __future__ import annotations

import argparse
import sys
import threading
from pathlib import Path

from lightflow.app.errors import ConfigError, FrameError

HELP = "reconstruct depth from a recording (every frame, in order)"

DESCRIPTION = """\
Run the depth pipeline over every frame of a recording folder (REC with
recording.json and frames/), in order and without dropping any, and send the
results to Rerun and/or export files.  Frames that are missing, unreadable or of
the wrong size are skipped and listed at the end.  A recording that lists no
frames, or whose timestamps do not increase, is refused before any work.
--export-ply writes points in world axes (y up) coloured by depth.  The file
formats are described in docs/formats.md.

Exit status: 0 when every frame was replayed; 2 when any frame was bad (the
good ones are still processed and written), when the recording or the rig is
malformed, or when an output cannot be written (e.g. a full disk); 130 when
stopped with Ctrl-C."""

EPILOG = """\
examples:
  lightflow replay rec/ --rrd out/rec.rrd            # then: rerun out/rec.rrd
  lightflow replay rec/ --spawn --compress           # live in a Rerun viewer
  lightflow replay rec/ --rig calibrated.json --export-depth out/depth --export-ply out/ply
  lightflow replay rec/ --stride 1 --smoothing 20 --export-depth out/depth"""


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


def add_pipeline_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--stride", type=int, choices=(1, 2, 4), default=4,
        help="analysis grid stride in pixels (1 = finest, slowest; default 4)",
    )  # fmt: skip
    p.add_argument(
        "--smoothing", type=float, metavar="PX",
        help="sigma of the flow-ratio smoothing in camera pixels (default: the pipeline's)",
    )  # fmt: skip


def pipeline_config(args: argparse.Namespace):
    """The :class:`PipelineConfig` the options ask for."""
    from lightflow.app.flow import FlowParams
    from lightflow.app.pipeline import PipelineConfig

    smoothing = getattr(args, "smoothing", None)
    if smoothing is None:
        return PipelineConfig(stride=args.stride)
    if not smoothing >= 0:
        raise ConfigError(f"--smoothing: expected a non-negative number of pixels, got {smoothing}")
    return PipelineConfig(stride=args.stride, flow=FlowParams(smoothing_px=smoothing))


def make_pipeline(rig, args: argparse.Namespace):
    """The depth pipeline, showing progress while its LUT is built (first use of a rig)."""
    from lightflow.app.pipeline import DepthPipeline
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


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "replay",
        help=HELP,
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("recording", metavar="REC", help="recording folder (holds recording.json)")
    p.add_argument("--rig", metavar="RIG", help="rig file overriding the recording's own rig")
    add_output_options(p)
    add_pipeline_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from lightflow.app.recording import timestamp_problems
    from lightflow.app.rig import resolve_rig
    from lightflow.app.runner import Runner
    from lightflow.app.status import StatusLine
    from lightflow.drivers.replay import RecordedCamera

    rig = resolve_rig(args.rig) if args.rig else None
    if rig is not None:
        check_rig_fits_recording(rig, args.rig, args.recording)
    camera = RecordedCamera(args.recording, rig=rig)
    rig = camera.rig
    n = len(camera.recording.frames)
    if n == 0:
        raise FrameError(f"{Path(args.recording) / 'recording.json'}: lists no frames")
    disorder = timestamp_problems(camera.recording)
    if disorder:
        more = f" (and {len(disorder) - 1} more)" if len(disorder) > 1 else ""
        raise ConfigError(f"{disorder[0]}{more}; check it with `lightflow verify`")
    cam = rig.camera
    print(f"replaying {n} frames of {cam.width}x{cam.height} from {args.recording}", flush=True)
    pipeline = make_pipeline(rig, args)
    sinks = build_sinks(args, rig)
    if not sinks:
        print("note: no output option given: computing depth only (see --help)", file=sys.stderr)
    status = StatusLine(total=n)
    runner = Runner(camera, pipeline, sinks, on_stats=status, lossless=True,
                    count_gaps=False,  # a gap is a bad frame, listed separately
                    on_warning=lambda text: print(f"\nwarning: {text}", file=sys.stderr,
                                                  flush=True))  # fmt: skip
    with camera:
        stats = runner.run(threading.Event())
    if stats.frames_done == 0:
        first = camera.bad_frames[0] if camera.bad_frames else "no frame was delivered"
        raise FrameError(f"{args.recording}: none of the {n} frames could be replayed ({first})")
    status.finish(stats, camera.bad_frames)
    describe_outputs(sinks)
    if runner.interrupted:
        print("stopped early (Ctrl-C): outputs hold the frames processed so far", file=sys.stderr)
        return 130
    if camera.bad_frames:
        # the good frames are done; the bad ones are input errors all the same
        print(f"lightflow: error: {len(camera.bad_frames)} of {n} frames could not be "
              f"replayed (listed above)", file=sys.stderr)  # fmt: skip
        return 2
    return 0
