"""Live capture against Aravis's GigE Vision simulator: frames lost, dropped, recorded.

Run inside a private network namespace (``make bench-capture`` does)::

    unshare --net sh -c 'ip link set lo up && .venv/bin/python tests/bench_capture.py'

Each run is a cold ``lightflow capture --record --lossless`` (a new process,
so kernels compile and tables load as a user's first run does), optionally
with a CPU hog on one core.  With ``--scene NAME`` the simulator streams frames
of that scene rendered for the bench's rig (``lightflow simulate``), so that the
pipeline measures real projected lines instead of Aravis's test pattern.  It
prints one line per run and exits 1 if any run lost or dropped a recorded frame.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from aravis_sim import SIM_ADDRESS, Simulator, private_netns_problem

from lightflow.app.core.rig import load_rig, rig_from_dict

RIG = Path(__file__).resolve().parents[1] / "app" / "rigs" / "two-projector.json"


def scaled_rig(width: int, height: int, out: Path) -> Path:
    """The example rig with its camera scaled to ``width`` x ``height``."""
    d = load_rig(RIG).to_dict()
    cam = d["camera"]
    sx, sy = width / cam["width"], height / cam["height"]
    K = np.array(cam["K"])
    K[0] *= sx
    K[1] *= sy
    K[0, 2] += 0.5 * sx - 0.5
    K[1, 2] += 0.5 * sy - 0.5
    cam.update(width=width, height=height, K=K.tolist())
    out.write_text(json.dumps(rig_from_dict(d, "bench rig").to_dict()))
    return out


def one_run(rig: Path, fps: float, frames: int, rerun: bool, work: Path, i: int,
            stride: int | None = None) -> dict:  # fmt: skip
    rec = work / f"rec{i}"
    cmd = [sys.executable, "-m", "lightflow.app.cli", "capture", "--camera",
           f"aravis:{SIM_ADDRESS}", "--rig", str(rig), "--exposure", "4", "--fps", str(fps),
           "--frames", str(frames), "--record", str(rec), "--lossless"]  # fmt: skip
    if rerun:
        cmd += ["--rrd", str(work / f"run{i}.rrd"), "--compress"]
    if stride is not None:
        cmd += ["--stride", str(stride)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    text = proc.stdout + proc.stderr
    lost = re.search(r"lost by the camera (\d+)", text)
    done = re.search(r"processed (\d+) of (\d+) frames", text)
    drops = re.search(r"dropped (\d+) \(", text)
    listed = json.loads((rec / "recording.json").read_text())["frames"] if rec.exists() else []
    ids = [int(Path(f["file"]).stem) for f in listed]
    consecutive = bool(ids) and ids == list(range(ids[0], ids[0] + len(ids)))
    return {
        "exit": proc.returncode,
        "lost": int(lost.group(1)) if lost else -1,
        "processed": int(done.group(1)) if done else -1,
        "depth_skipped": int(drops.group(1)) if drops else -1,
        "recorded": len(ids),
        "consecutive": consecutive,
        "tail": proc.stderr.strip().splitlines()[-1:] if proc.returncode else [],
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", default="512x512")
    p.add_argument("--fps", type=float, default=50)
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--hog", action="store_true", help="keep one core busy during the runs")
    p.add_argument("--rerun", action="store_true", help="also write a compressed .rrd")
    p.add_argument("--stride", type=int, help="the pipeline's analysis grid stride (default: "
                   "capture's)")  # fmt: skip
    p.add_argument("--scene", help="stream 3 rendered frames of this scene (default: Aravis's "
                   "test pattern, which has no lines)")  # fmt: skip
    args = p.parse_args()
    problem = private_netns_problem()
    if problem:
        print(problem, file=sys.stderr)
        return 2
    w, h = (int(v) for v in args.size.split("x"))
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        rig = scaled_rig(w, h, work / "rig.json")
        frames_from = None
        if args.scene:
            frames_from = str(work / "scene")
            subprocess.run([sys.executable, "-m", "lightflow.app.cli", "simulate", "--scene",
                            args.scene, "--rig", str(rig), "--frames", "3", "--out", frames_from],
                           check=True, stdout=subprocess.DEVNULL)  # fmt: skip
        with Simulator(frames_from=frames_from):
            bad = runs(args, rig, work)
    return 1 if bad else 0


def runs(args, rig: Path, work: Path) -> int:
    """Run the captures, print a line each; the number that lost or dropped a recorded frame."""
    bad = 0
    hog = subprocess.Popen([sys.executable, "-c", "while 1: pass"]) if args.hog else None
    try:
        for i in range(args.runs):
            r = one_run(rig, args.fps, args.frames, args.rerun, work, i, args.stride)
            ok = (r["exit"] == 0 and r["lost"] == 0 and r["recorded"] == args.frames
                  and r["consecutive"])  # fmt: skip
            bad += not ok
            print(f"{args.size} at {args.fps:g} fps, {args.frames} frames"
                  f"{', ' + args.scene if args.scene else ''}{', hog' if hog else ''}"
                  f"{', rrd' if args.rerun else ''}"
                  f"{f', stride {args.stride}' if args.stride else ''}: exit {r['exit']}, "
                  f"lost by the camera {r['lost']}, recorded {r['recorded']} "
                  f"(consecutive ids: {'yes' if r['consecutive'] else 'NO'}), depth on "
                  f"{r['processed']} (skipped {r['depth_skipped']}) {' '.join(r['tail'])}",
                  flush=True)  # fmt: skip
    finally:
        if hog is not None:
            hog.kill()
            hog.wait()
    return bad


if __name__ == "__main__":
    sys.exit(main())
