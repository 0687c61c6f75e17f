"""``lightflow replay``: reconstruct depth from a recording, losing no frame."""

from __future__ import annotations

import argparse
import sys
import threading
from pathlib import Path

from lightflow.app.core.errors import ConfigError, FrameError
from lightflow.app.options import (
    add_output_options,
    add_pipeline_options,
    build_sinks,
    check_rig_fits_recording,
    describe_outputs,
    make_pipeline,
)

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
stopped early with Ctrl-C or by closing the Rerun viewer of --spawn."""

EPILOG = """\
examples:
  lightflow replay rec/ --rrd out/rec.rrd            # then: rerun out/rec.rrd
  lightflow replay rec/ --spawn --compress           # live in a Rerun viewer
  lightflow replay rec/ --rig calibrated.json --export-depth out/depth --export-ply out/ply
  lightflow replay rec/ --stride 1 --smoothing 20 --export-depth out/depth"""


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
    from lightflow.app.core.rig import resolve_rig
    from lightflow.app.recording import timestamp_problems
    from lightflow.app.replay_camera import RecordedCamera
    from lightflow.app.runner import Runner
    from lightflow.app.status import (
        StatusLine,
        describe_blur,
        describe_crosstalk,
        describe_response,
    )

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
    print(describe_blur(pipeline), file=sys.stderr)
    print(describe_response(pipeline), file=sys.stderr)
    print(describe_crosstalk(pipeline), file=sys.stderr)
    describe_outputs(sinks)
    if runner.interrupted or (runner.stopped and runner.closed_output):
        why = "Ctrl-C" if runner.interrupted else runner.closed_output
        print(f"stopped early ({why}): outputs hold the frames processed so far", file=sys.stderr)
        return 130
    if camera.bad_frames:
        # the good frames are done; the bad ones are input errors all the same
        print(f"lightflow: error: {len(camera.bad_frames)} of {n} frames could not be "
              f"replayed (listed above)", file=sys.stderr)  # fmt: skip
        return 2
    return 0
