"""``lightflow calibrate``: calibrate camera and projectors from a Gray-code session.

Offline: ``lightflow calibrate CAL/ --out rig.json`` reads a session folder
(formats.md section 4), prints the report and writes the rig.  When the session
has a ``ground_truth.json`` beside it (a simulated session), the errors against
the true rig are printed too.

Live: ``lightflow calibrate --camera URI --screens ... --board 9x6@0.030 --out CAL/``
captures a session pose by pose, then calibrates it (writing ``CAL/rig.json``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "calibrate",
        help="calibrate camera and projectors from a Gray-code session",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("session", nargs="?", type=Path,
                   help="session folder to calibrate offline (contains session.json)")
    p.add_argument("--out", type=Path, required=True,
                   help="rig file to write (offline) or session folder to capture into (live)")
    live = p.add_argument_group("live capture")
    live.add_argument("--camera", metavar="URI", help="camera to capture with")
    live.add_argument("--screens", metavar="S1[,S2]",
                      help="comma-separated screen index or name for each projector, in the "
                      "rig's projector order")
    live.add_argument("--board", default="9x6@0.030", metavar="COLSxROWS@SQUARE_M",
                      help="checkerboard inner corners and square side (default 9x6@0.030)")
    live.add_argument("--rig", type=Path,
                      help="rig file giving the projectors' sizes and patterns (live)")
    live.add_argument("--poses", type=int, default=10, help="poses to capture (default 10)")
    p.set_defaults(func=run)


def _progress(stage: str, i: int, n: int) -> None:
    end = "\n" if i == n else ""
    print(f"\r{stage}: {i}/{n}", end=end, file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    from lightflow.app.errors import ConfigError

    if args.session is not None and args.camera is not None:
        raise ConfigError("calibrate: give either a session folder or --camera, not both")
    if args.session is None:
        if args.camera is None:
            raise ConfigError("calibrate: give a session folder to calibrate, or --camera "
                              "to capture one")
        return run_live(args)
    return calibrate_offline(args.session, args.out, _progress)


def calibrate_offline(session: Path, out: Path, progress=None) -> int:
    """Calibrate a session folder, print the report, write the rig."""
    from lightflow.app.rig import read_json, rig_from_dict, save_rig
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
    return 0


def run_live(args: argparse.Namespace) -> int:
    """Capture a session with a camera and projector windows, then calibrate it."""
    import threading

    import numpy as np

    from lightflow.app.commands.project import parse_screens
    from lightflow.app.errors import ConfigError
    from lightflow.app.rig import resolve_rig
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
        from lightflow.drivers import open_camera
    except ImportError:
        raise ConfigError("calibrate --camera: this build has no camera factory "
                          "(lightflow.drivers.open_camera)") from None
    from lightflow.drivers.projector import ProjectorWindows

    camera = open_camera(args.camera)
    outputs = ProjectorWindows([(p.name, s, np.zeros((p.height, p.width, 3), np.uint8))
                                for p, s in zip(specs, selectors, strict=True)])
    stop = threading.Event()
    result: dict = {}

    def worker() -> None:
        try:
            result["session"] = calibrate_live(camera, outputs, board, specs, args.out,
                                               args.poses)
        except BaseException as exc:  # handed to the main thread
            result["error"] = exc
        finally:
            stop.set()

    with camera, outputs:
        thread = threading.Thread(target=worker, name="calibrate-live", daemon=True)
        thread.start()
        outputs.run(stop)
        thread.join(timeout=10)
    if "error" in result:
        raise result["error"]
    if "session" not in result:
        raise ConfigError("calibrate: capture stopped before it finished")
    return calibrate_offline(args.out, args.out / "rig.json", _progress)
