"""`lightflow calibrate`: calibrate camera and projectors from a Gray-code session."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

DESCRIPTION = """\
Calibrate the camera and the projectors of a rig from a Gray-code session and
write the rig file that `lightflow capture` and `lightflow replay` use.

Offline: give a session folder (CAL/session.json with the camera frames, see
formats.md section 4).  The report lists the RMS reprojection error of every
device per pose, the poses left out and why, warnings (too few good poses, too
little tilt variety) and placement advice.  When CAL/gamma/ holds a grey ramp,
each projector's gamma is measured and reported.  A simulated session (with
CAL/ground_truth.json) is also compared with the true rig.

Live: give --camera, --rig (projector sizes and patterns) and --screens.
Place the board as asked, pose by pose: each projector shows the Gray-code
sequence while the camera records; afterwards each projector shows a grey
ramp on a plain light surface.  The session is written to --out and then
calibrated into --out/rig.json.  --rrd FILE or --spawn shows the progress in
Rerun: the camera image with the detected corners, the decoded projector
column/row maps and the board poses captured so far.

Examples:
  lightflow simulate --calibration --poses 8 --out cal
  lightflow calibrate cal --out rig.json
  lightflow calibrate --camera v4l2:/dev/video0 --rig my-rig.json --screens 1,2 \\
      --board 9x6@0.030 --poses 10 --out cal --spawn"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "calibrate",
        help="calibrate camera and projectors from a Gray-code session",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("session", nargs="?", type=Path,
                   help="session folder to calibrate offline (contains session.json)")
    p.add_argument("--out", type=Path, required=True,
                   help="rig file to write (offline) or session folder to capture into (live)")
    live = p.add_argument_group("live capture")
    live.add_argument("--camera", metavar="URI",
                      help="camera to capture with: aravis:ID|ADDRESS or v4l2:/dev/videoN")
    live.add_argument("--screens", metavar="S1[,S2]",
                      help="comma-separated screen index or name for each projector, in the "
                      "rig's projector order")
    live.add_argument("--board", default="9x6@0.030", metavar="COLSxROWS@SQUARE_M",
                      help="checkerboard inner corners and square side (default 9x6@0.030)")
    live.add_argument("--rig", type=Path,
                      help="rig file giving the projectors' sizes and patterns (live)")
    live.add_argument("--poses", type=int, default=10, help="poses to capture (default 10)")
    view = live.add_mutually_exclusive_group()
    view.add_argument("--rrd", type=Path, metavar="FILE",
                      help="log the capture progress to a Rerun .rrd file")
    view.add_argument("--spawn", action="store_true",
                      help="show the capture progress in a Rerun viewer window")
    p.set_defaults(func=run)


def _progress(stage: str, i: int, n: int) -> None:
    end = "\n" if i == n else ""
    print(f"\r{stage}: {i}/{n}", end=end, file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    from lightflow.app.core.errors import ConfigError

    if args.session is not None and args.camera is not None:
        raise ConfigError("calibrate: give either a session folder or --camera, not both")
    if args.session is not None and (args.rrd is not None or args.spawn):
        raise ConfigError("calibrate: --rrd and --spawn show a live capture; give them with "
                          "--camera")
    if args.session is None:
        if args.camera is None:
            raise ConfigError("calibrate: give a session folder to calibrate, or --camera "
                              "to capture one")
        return run_live(args)
    return calibrate_offline(args.session, args.out, _progress)


def calibrate_offline(session: Path, out: Path, progress=None) -> int:
    """Calibrate a session folder, print the report (with CAL/gamma/ measured), write the rig."""
    from lightflow.app.core.rig import read_json, rig_from_dict, save_rig
    from lightflow.calibration.pipeline import calibrate_session
    from lightflow.calibration.report import compare_rigs, rigcheck_lines
    from lightflow.calibration.simulate import TRUTH_FILE

    rig, report = calibrate_session(session, progress=progress)
    root = session.parent if session.suffix == ".json" else session
    truth_file = root / TRUTH_FILE
    if truth_file.is_file():
        truth = rig_from_dict(read_json(truth_file).get("rig"), f"{truth_file}: rig")
        report.comparison = compare_rigs(rig, truth)
    for line in report.summary_lines():
        print(line)
    for line in rigcheck_lines(rig):
        print(line)
    save_rig(rig, out)
    print(f"wrote {out}")
    # the placement as pictures: dh/dz, expected error, usable pixels, overlap
    from lightflow.app.options import write_images
    from lightflow.app.rigcheck import check_rig

    pictures = out.with_name(out.stem + "-placement")
    paths = write_images(check_rig(rig).images, pictures)
    print(f"wrote {len(paths)} placement images to {pictures}/ (see `lightflow rig check`)")
    return 0


def run_live(args: argparse.Namespace) -> int:
    """Capture a session with a camera and projector windows, then calibrate it."""
    import threading

    import numpy as np

    from lightflow.app.core.errors import ConfigError
    from lightflow.app.core.rig import resolve_rig
    from lightflow.app.options import parse_screens
    from lightflow.calibration.live import calibrate_live
    from lightflow.calibration.session import Board, ProjectorSpec

    if args.rig is None or args.screens is None:
        raise ConfigError("calibrate --camera: also give --rig (projector sizes and patterns) "
                          "and --screens")
    rig = resolve_rig(args.rig)
    board = Board.parse(args.board)
    specs = [ProjectorSpec(p.name, p.width, p.height, p.patterns) for p in rig.projectors]
    selectors = parse_screens(args.screens, [p.name for p in specs])
    try:
        from lightflow.app.cameras import open_camera
    except ImportError:
        raise ConfigError("calibrate --camera: this build has no camera factory "
                          "(lightflow.drivers.open_camera)") from None
    from lightflow.drivers.projector import ProjectorWindows

    sink = None
    if args.rrd is not None or args.spawn:
        from lightflow.app.sinks.calibration_sink import CalibrationSink

        sink = CalibrationSink(board, [p.name for p in specs],
                               "rrd" if args.rrd is not None else "spawn", path=args.rrd)
    try:
        camera = open_camera(args.camera)
    except BaseException:
        if sink is not None:
            sink.close()
        raise
    outputs = ProjectorWindows([(p.name, s, np.zeros((p.height, p.width, 3), np.uint8))
                                for p, s in zip(specs, selectors, strict=True)])
    stop = threading.Event()
    result: dict = {}

    def worker() -> None:
        try:
            result["session"] = calibrate_live(camera, outputs, board, specs, args.out,
                                               args.poses,
                                               on_pose=sink.log if sink is not None else None)
        except BaseException as exc:  # handed to the main thread
            result["error"] = exc
        finally:
            stop.set()

    try:
        with camera, outputs:
            thread = threading.Thread(target=worker, name="calibrate-live", daemon=True)
            thread.start()
            outputs.run(stop)
            thread.join(timeout=10)
    finally:
        if sink is not None:
            sink.close()
            print(sink.describe())
    if "error" in result:
        raise result["error"]
    if "session" not in result:
        raise ConfigError("calibrate: capture stopped before it finished")
    return calibrate_offline(args.out, args.out / "rig.json", _progress)
