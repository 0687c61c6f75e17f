"""``lightflow capture``: live depth from a camera while the projectors show the patterns."""

from __future__ import annotations

import argparse
import sys
import threading

from lightflow.app.core.errors import ConfigError, FrameError
from lightflow.app.options import (
    add_output_options,
    add_pipeline_options,
    build_sinks,
    check_rig_fits_recording,
    close_all,
    describe_outputs,
    make_pipeline,
)

HELP = "capture live: camera -> depth -> Rerun/files, optionally showing the patterns"

DESCRIPTION = """\
Capture frames from a camera, compute depth live and send it to Rerun and/or
files, optionally recording the raw frames.  The camera is set to the rig's
image size and to the exposure given (the value the camera really uses is read
back and printed).  `--exposure auto` first adjusts the exposure from the
measured band lengths (long bands, clearly shorter than the line interval)
and says what it chose and why; the exposure then stays fixed for the run so
that a recording has one exposure.

With --screens, the rig's patterns are shown fullscreen on those screens for
the whole run (as `lightflow project` does).  Ctrl-C, Esc in a pattern window
or closing it stops cleanly: queued frames are finished and every output,
including the recording, is complete.  So does closing the Rerun viewer of
--spawn.  When processing falls behind, the oldest frames are dropped (counted
in the status line); --record still gets every frame the camera delivers.

Acquisition never waits on processing: the driver's own thread keeps the
camera's buffers cycling, and before streaming starts every compiled kernel,
the depth table and the blur tables are loaded ("warming up").  With
--lossless the recording is lossless: the recorder never drops a frame (it
buffers up to --record-buffer MiB in memory and says at once when the disk is
slower than the camera); depth may still skip frames, counted and shown.

Exit status: 0 when the run ended (camera exhausted, --frames reached,
Ctrl-C); 2 on bad input, a missing or lost device, or a failed output.

Cameras: aravis:ID|ADDRESS, v4l2:/dev/videoN, synthetic:SCENE (rendered, no
hardware needed), replay:REC (a recording played as a camera)."""

EPILOG = """\
examples:
  lightflow capture --camera aravis:192.168.1.20 --rig rig.json --screens 1,2 \\
      --exposure auto --record rec/ --spawn
  lightflow capture --camera v4l2:/dev/video0 --rig rig.json --exposure 8 --rrd out/live.rrd
  lightflow capture --camera synthetic:ball --rig app/rigs/two-projector.json \\
      --frames 30 --rrd out/ball.rrd --record out/ball-rec"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "capture",
        help=HELP,
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--camera", required=True, metavar="URI",
                   help="aravis:ID|ADDRESS, v4l2:/dev/videoN, synthetic:SCENE or replay:REC")
    p.add_argument("--rig", metavar="RIG",
                   help="rig file (required, except for replay: which carries its rig)")
    p.add_argument("--screens", metavar="S1[,S2]",
                   help="show each projector's pattern on these screens (see lightflow project)")
    p.add_argument("--display", metavar=":N", help="X display for --screens (default: $DISPLAY)")
    p.add_argument("--allow-size-mismatch", action="store_true",
                   help="accept a screen larger than the projector image (drawn 1:1 top-left)")
    p.add_argument("--exposure", metavar="MS|auto",
                   help="exposure in milliseconds, or auto (default: leave the camera's)")
    p.add_argument("--gain", type=float, metavar="G",
                   help="camera gain (Aravis: dB, V4L2: the device's units; default: leave it)")
    p.add_argument("--record", metavar="DIR", help="also record the raw frames into a new folder")
    p.add_argument("--frames", type=int, metavar="N", help="stop after N frames (default: run "
                   "until Ctrl-C or the camera ends)")
    p.add_argument("--queue-size", type=int, default=4, metavar="N",
                   help="frames buffered between the threads (default 4)")
    p.add_argument("--lossless", action="store_true",
                   help="the recording gets every frame the camera delivers, whatever the disk "
                   "does (depth may skip frames, counted); replay/synthetic cameras: depth too")
    p.add_argument("--record-buffer", type=float, default=1024, metavar="MIB",
                   help="memory for frames waiting to be written by --record (default 1024)")
    p.add_argument("--fps", type=float, metavar="FPS",
                   help="camera frame rate (default: the camera's; synthetic: 30)")
    p.add_argument("--control-wait", type=float, default=10.0, metavar="S",
                   help="aravis: how long to wait for a GigE camera still controlled by another "
                   "client, e.g. a crashed lightflow until its heartbeat times out (default 10)")
    add_output_options(p)
    add_pipeline_options(p)
    p.set_defaults(func=run)


def parse_exposure(text: str | None) -> float | str | None:
    """``auto``, seconds from a number of milliseconds, or None."""
    if text is None or text == "auto":
        return text
    try:
        ms = float(text)
    except ValueError:
        raise ConfigError(f"--exposure: expected milliseconds or 'auto', got {text!r}") from None
    if not ms > 0:
        raise ConfigError(f"--exposure: expected a positive number of milliseconds, got {text}")
    return ms / 1e3


def run(args: argparse.Namespace) -> int:
    from lightflow.app.cameras import open_camera
    from lightflow.app.core.rig import resolve_rig
    from lightflow.app.exposure import BlurAwareExposure, settle_exposure
    from lightflow.app.recording import RecordingWriter
    from lightflow.app.runner import Runner
    from lightflow.app.status import (
        StatusLine,
        describe_blur,
        describe_crosstalk,
        describe_response,
        describe_speed,
    )

    exposure = parse_exposure(args.exposure)
    if args.frames is not None and args.frames <= 0:
        raise ConfigError(f"--frames: expected a positive number, got {args.frames}")
    if args.fps is not None and not args.fps > 0:
        raise ConfigError(f"--fps: expected a positive frame rate, got {args.fps}")
    scheme = args.camera.partition(":")[0]
    if args.rig is None and scheme != "replay":
        raise ConfigError("--rig: required with this camera (the rig file, rig.json)")
    rig = resolve_rig(args.rig) if args.rig else None
    if scheme == "replay" and rig is not None:
        check_rig_fits_recording(rig, args.rig, args.camera.partition(":")[2])
    opts = {}
    if scheme == "synthetic":
        opts = {"frames": args.frames, "fps": args.fps or 30.0}
    if scheme == "aravis":
        if not args.control_wait >= 0:
            raise ConfigError(f"--control-wait: expected seconds >= 0, got {args.control_wait}")
        opts = {"control_wait_s": args.control_wait}
    camera = open_camera(args.camera, rig, **opts)
    rig = rig or camera.rig
    patterns = _pattern_output(args, rig)  # before the camera: a bad --screens fails fast

    with camera:
        w, h = rig.camera.width, rig.camera.height
        camera.set_size(w, h)
        rate = ""
        set_rate = getattr(camera, "set_frame_rate", None)
        if args.fps and set_rate is not None:
            rate = f", {set_rate(args.fps):.4g} fps"
        print(f"camera {camera.uri}: {w}x{h}{rate}", flush=True)
        pipeline = make_pipeline(rig, args)
        if args.gain is not None:
            if not hasattr(camera, "set_gain"):
                raise ConfigError(f"--gain: {args.camera} has no gain control")
            got = camera.set_gain(args.gain)
            print(f"gain: asked {args.gain:g}, camera uses {got:g}", flush=True)
        if exposure == "auto":
            controller = BlurAwareExposure(max_s=1.0 / (args.fps or 30.0))
            chosen, decisions = settle_exposure(camera, pipeline, controller, log=print)
            why = decisions[-1].reason if decisions else "no frame to measure"
            print(f"exposure (auto): {chosen * 1e3:.3g} ms ({why})", flush=True)
        elif exposure is not None:
            got = camera.set_exposure(exposure)
            print(f"exposure: asked {exposure * 1e3:.3g} ms, camera uses {got * 1e3:.3g} ms",
                  flush=True)
        else:
            print(f"exposure: {camera.exposure_s * 1e3:.3g} ms (the camera's)", flush=True)
        # before the camera streams: a first-frame stall would back up into the camera
        print("warming up (compiling kernels, loading the depth and blur tables) ...", flush=True)
        print(f"warmed up in {pipeline.warm_up():.1f} s", flush=True)
        sinks = build_sinks(args, rig)
        try:
            recorder = None
            if args.record:
                frame_mib = w * h * 3 * 2 / 2**20  # worst case: 16-bit samples
                recorder = RecordingWriter(
                    args.record, rig, camera.exposure_s,
                    queue_size=max(16, int(args.record_buffer / frame_mib)),
                    # lossless: block the capture thread (the driver keeps buffering) rather
                    # than drop; otherwise absorb short disk stalls, then drop and count
                    put_timeout_s=None if args.lossless else 0.5,
                )  # fmt: skip
        except BaseException:
            close_all(sinks)
            raise
        status = StatusLine(total=args.frames)
        # A live camera must never wait for depth: only cameras that cannot lose
        # frames (replay, synthetic) may block on a full queue.
        blocking = args.lossless and scheme in ("replay", "synthetic")
        runner = Runner(
            camera, pipeline, sinks, queue_size=args.queue_size, on_stats=status,
            lossless=blocking, recorder=recorder, max_frames=args.frames,
            on_warning=lambda text: print(f"warning: {text}", file=sys.stderr, flush=True),
        )  # fmt: skip
        stop = threading.Event()
        print("capturing; Ctrl-C to stop", flush=True)
        if patterns is None:
            stats = runner.run(stop)
        else:
            stats = _run_with_patterns(runner, patterns, stop)
    bad = getattr(camera, "bad_frames", [])
    status.finish(stats, bad)
    hint = describe_speed(stats, pipeline.config.stride)
    if hint:
        print(hint, file=sys.stderr)
    print(describe_blur(pipeline), file=sys.stderr)
    print(describe_response(pipeline), file=sys.stderr)
    print(describe_crosstalk(pipeline), file=sys.stderr)
    if stats.frames_done == 0 and bad:
        raise FrameError(f"{camera.uri}: no frame could be used ({bad[0]})")
    describe_outputs(sinks)
    if recorder is not None:
        dropped = f", {recorder.dropped} DROPPED (disk too slow)" if recorder.dropped else ""
        print(f"recording: {recorder.written} frames in {args.record}{dropped}")
    if runner.closed_output:
        print(f"stopped: {runner.closed_output}; every output is complete", file=sys.stderr)
    elif runner.stopped or runner.interrupted:
        print("stopped; every output is complete", file=sys.stderr)
    return 0


def _pattern_output(args: argparse.Namespace, rig):
    if not args.screens:
        return None
    from lightflow.app.core.patterns import pattern_image
    from lightflow.app.options import parse_screens
    from lightflow.drivers.projector import ProjectorWindows

    selectors = parse_screens(args.screens, [p.name for p in rig.projectors])
    return ProjectorWindows(
        [(p.name, s, pattern_image(p)) for p, s in zip(rig.projectors, selectors, strict=True)],
        display=args.display,
        allow_size_mismatch=args.allow_size_mismatch,
    )


def _run_with_patterns(runner, windows, stop: threading.Event):
    """pyglet keeps the main thread; the workers run meanwhile; either side can stop both."""
    with windows:
        for name, screen in windows.placements:
            print(f"projector {name} -> {screen.describe()}", flush=True)
        runner.start(stop)
        try:
            windows.run(stop)  # returns when stop is set: window closed, Esc, or run ended
        except KeyboardInterrupt:
            runner.interrupted = True
        finally:
            stop.set()
            stats = runner.join()
    return stats
