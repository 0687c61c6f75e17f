"""``lightflow verify REC``: check a recording against the format contract."""

from __future__ import annotations

import argparse

from lightflow.app.core.errors import ConfigError, FrameError
from lightflow.app.core.rig import resolve_rig
from lightflow.app.recording import (
    FRAMES_DIR,
    Recording,
    load_frame,
    read_recording,
    repair_recording,
    timestamp_problems,
    unlisted_files,
)

DESCRIPTION = """\
Check a recording folder (recording.json + frames/*.png) before replaying it or
handing it on: recording.json must follow the format exactly (with a valid rig
and a positive exposure_s), every listed frame must exist, be a readable RGB
PNG of the camera size (8 or 16 bits per channel), appear once, and the
timestamps t must increase.  A recording that lists no frame, frame files
that recording.json does not list and leftover temporary files are reported
too: a killed `lightflow capture --record` leaves them.  `--repair` then lists
every complete frame the recorder had written (from frames.index) and removes
partial files; run verify again afterwards.  The format is described in
docs/formats.md (section 2).

Every problem is printed on its own line.  Exit status: 0 when the recording
is clean, 2 when anything is wrong."""

EPILOG = """\
examples:
  lightflow verify rec/                 # exit 0 when clean, 2 with one line per problem
  lightflow verify rec/ --rig rig.json  # check the frames against another rig's camera size
  lightflow verify rec/ --repair        # after a crash: relist complete frames"""



def register(subparsers) -> None:
    p = subparsers.add_parser(
        "verify",
        help="check a recording folder for problems",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("recording", metavar="REC", help="recording folder (holds recording.json)")
    p.add_argument(
        "--rig",
        metavar="RIG.json",
        help="check the frames against this rig's camera instead of the embedded rig "
        "(a file or an example rig name such as two-projector)",
    )
    p.add_argument("--repair", action="store_true",
                   help="relist complete frames a crash left unlisted and remove partial files")
    p.set_defaults(func=run)


def check_recording(rec: Recording) -> list[str]:
    """Everything wrong with a parsed recording, one line each (empty when clean).

    Parameters
    ----------
    rec : Recording
        A recording whose ``recording.json`` already parsed.
    """
    problems: list[str] = []
    src = rec.json_path
    if not rec.frames:
        problems.append(f"{src}: frames: the recording lists no frame")
    unlisted, temporary = unlisted_files(rec)
    if unlisted:
        problems.append(
            f"{rec.root / FRAMES_DIR}: {len(unlisted)} file(s) not listed in recording.json "
            f"(first {unlisted[0].name}; a crash while recording? `lightflow verify --repair`)"
        )
    for p in temporary:
        problems.append(f"{p}: leftover temporary file (an interrupted write; --repair removes it)")
    # a frame listed twice never gets here: read_recording refuses it
    problems += timestamp_problems(rec)
    for i in range(len(rec.frames)):
        try:
            load_frame(rec, i)
        except FrameError as exc:
            problems.append(str(exc))
    return problems


def run(args: argparse.Namespace) -> int:
    rig = resolve_rig(args.rig) if args.rig else None
    if args.repair:
        added, removed = repair_recording(args.recording)
        print(f"{args.recording}: relisted {added} frame(s), removed {len(removed)} partial "
              f"or temporary file(s)")
    try:
        rec = read_recording(args.recording, rig)
    except ConfigError as exc:
        # a broken recording.json is a finding of verify, not a failure to run it
        print(f"PROBLEM {exc}")
        print(f"{args.recording}: 1 problem (recording.json is unreadable, frames not checked)")
        return 2
    problems = check_recording(rec)
    for line in problems:
        print(f"PROBLEM {line}")
    cam = rec.rig.camera
    summary = (
        f"{rec.root}: {len(rec.frames)} frames, {cam.width}x{cam.height}, "
        f"exposure {rec.exposure_s * 1e3:g} ms"
    )
    if problems:
        print(f"{summary}: {len(problems)} problem{'s' if len(problems) > 1 else ''}")
        return 2
    print(f"{summary}: OK")
    return 0
