"""``lightflow demo``: render a synthetic moving scene, reconstruct it, show or save it."""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import threading
from pathlib import Path

import numpy as np

from lightflow.app.errors import ConfigError, DriverError

HELP = "render a moving scene, reconstruct its depth and show it (no hardware needed)"


DESCRIPTION = """\
Render a built-in moving scene as the camera of a rig would see it (projected
line patterns blurred by the motion, with sensor noise), reconstruct its depth
with the same pipeline as `lightflow capture`, and compare with the ground
truth.  With a display, the results open in a Rerun viewer; without one (or
with --no-viewer) they are written to OUT/demo.rrd, to open later with
`rerun OUT/demo.rrd`.  Runs in under a minute on two cores with the
defaults (the first run also builds and caches the depth tables)."""

EPILOG = """\
scenes: board, textured-board, tilted-board, ball, fan, two-balls
examples:
  lightflow demo                                    # fan, two projectors
  lightflow demo --scene ball --rig single-projector --frames 6
  lightflow demo --scale 0.5 --frames 20 --out out/ # half resolution, faster per frame"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "demo",
        help=HELP,
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--scene", default="fan", help="built-in scene (default fan)")
    p.add_argument("--rig", default="two-projector", metavar="NAME|PATH",
                   help="two-projector, single-projector or a rig file (default two-projector)")
    p.add_argument("--frames", type=int, default=3, metavar="N",
                   help="frames to render (default 3; each takes a few seconds to simulate)")
    p.add_argument("--scale", type=float, default=1.0, metavar="S",
                   help="camera resolution relative to the rig's (default 1: 1600x1200)")
    p.add_argument("--out", default="out", metavar="DIR",
                   help="where demo.rrd goes when no viewer is shown (default out/)")
    p.add_argument("--no-viewer", action="store_true",
                   help="write OUT/demo.rrd even when a display is available")
    p.add_argument("--fps", type=float, default=30.0, help="frame rate of the scene (default 30)")
    p.set_defaults(func=run, stride=4, smoothing=None)


class AccuracySink:
    """Compares each depth map with the renderer's ground truth (moving objects only).

    Static surfaces leave no blur, so no depth is expected there; the scores
    are over the pixels of moving objects (object id >= 2) lit by every projector.
    """

    def __init__(self, n_projectors: int):
        self.full_mask = (1 << n_projectors) - 1
        self.errors: list[np.ndarray] = []
        self.truth_pixels = 0
        self.estimated = 0
        self.frames = 0

    def write(self, result, stats) -> None:
        truth = result.frame.extras.get("truth")
        if truth is None:
            return
        self.frames += 1
        moving = (truth.object_id >= 2) & np.isfinite(truth.depth)
        moving &= (truth.lit & self.full_mask) == self.full_mask
        est = moving & np.isfinite(result.depth)
        self.truth_pixels += int(np.count_nonzero(moving))
        self.estimated += int(np.count_nonzero(est))
        self.errors.append(np.abs(result.depth[est] - truth.depth[est]).astype(np.float64))

    def close(self) -> None:
        """Nothing to flush."""

    def describe(self) -> str:
        if not self.truth_pixels:
            return "accuracy: no moving object was lit in these frames"
        cov = self.estimated / self.truth_pixels
        err = np.concatenate(self.errors) if self.errors else np.empty(0)
        if err.size == 0:
            return f"accuracy: no depth on the moving objects (coverage 0 of {self.frames} frames)"
        return (
            f"accuracy against ground truth over {self.frames} frames (moving, lit pixels): "
            f"median error {np.median(err) * 1e3:.1f} mm, 90th percentile "
            f"{np.percentile(err, 90) * 1e3:.1f} mm, coverage {100 * cov:.0f}%"
        )


def open_viewer_or_file(rig, out: Path, want_viewer: bool):
    """A RerunSink on a spawned viewer when a display allows it, else on OUT/demo.rrd."""
    from lightflow.app.sinks.rerun_sink import RerunSink

    if want_viewer and (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        try:
            return RerunSink(rig, "spawn", compress=True), True
        except DriverError as exc:
            print(f"note: no Rerun viewer ({exc}); writing a file instead", file=sys.stderr)
    return RerunSink(rig, "rrd", path=out / "demo.rrd", compress=True), False


def run(args: argparse.Namespace) -> int:
    from lightflow.app.rig import resolve_rig
    from lightflow.app.runner import Runner
    from lightflow.app.status import StatusLine
    from lightflow.drivers.scenes import get_scene
    from lightflow.drivers.synthetic import SyntheticCamera

    from .replay import close_all, make_pipeline

    if args.frames <= 0:
        raise ConfigError(f"--frames: expected a positive number, got {args.frames}")
    if not 0.05 <= args.scale <= 2:
        raise ConfigError(f"--scale: expected 0.05 .. 2, got {args.scale}")
    scene = get_scene(args.scene)
    rig = resolve_rig(args.rig)
    if args.scale != 1:
        rig = rig.scaled(args.scale)
    cam = rig.camera
    print(f"demo: scene {scene.name} ({scene.description}), {cam.width}x{cam.height} camera, "
          f"{len(rig.projectors)} projector(s), {args.frames} frames", flush=True)
    pipeline = make_pipeline(rig, args)
    out = Path(args.out)
    rerun_sink, spawned = open_viewer_or_file(rig, out, not args.no_viewer)
    accuracy = AccuracySink(len(rig.projectors))
    sinks = [rerun_sink, accuracy]
    try:
        camera = SyntheticCamera(rig, scene.name, frames=args.frames, fps=args.fps)
    except BaseException:
        close_all(sinks)
        raise
    print("rendering and reconstructing (each frame is simulated with motion blur) ...",
          flush=True)
    status = StatusLine(total=args.frames)
    runner = Runner(camera, pipeline, sinks, on_stats=status, lossless=True)
    with camera:
        stats = runner.run(threading.Event())
    status.finish(stats)
    print(accuracy.describe())
    print(rerun_sink.describe())
    if not spawned:
        # the viewer comes with rerun-sdk, next to this interpreter (.venv/bin)
        viewer = shutil.which("rerun") or str(Path(sys.executable).parent / "rerun")
        print(f"open it with:  {viewer} {out / 'demo.rrd'}")
    return 130 if runner.interrupted else 0
