"""``lightflow demo``: render a synthetic moving scene, reconstruct it, show or save it."""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import threading
import time
from pathlib import Path

import numpy as np

from lightflow.app.errors import ConfigError, DriverError

HELP = "render a moving scene, reconstruct its depth and show it (no hardware needed)"


DESCRIPTION = """\
Render a built-in moving scene as the camera of a rig would see it (projected
line patterns blurred by the motion, with sensor noise), reconstruct its depth
with the same pipeline as `lightflow capture`, and compare with the ground
truth.  The default scene is a fan spinning in front of a static wall: the
blades get depth, the wall (no motion, no blur) is rejected.  With a display
the results open in a Rerun viewer and are also kept in OUT/demo.rrd; without
one (or with --no-viewer) they go to OUT/demo.rrd only, to open later with
`rerun OUT/demo.rrd`.

The defaults render at a quarter of the rig's resolution (400x300 for the
example rigs): 36 frames, 1.2 s of motion.  Measured (CPU time, so that a
busy machine does not hide it): rendering a 400x300 fan frame takes about
1 CPU-second, a 1600x1200 board frame about 7 (use --scale 1 for that).  The
first run also compiles the renderer and the pipeline and builds the depth
tables, which are cached afterwards: on a heavily shared 2-core machine
(load 13) that took about 2 minutes, the 36 frames about 2 more."""

EPILOG = """\
scenes: board, textured-board, tilted-board, ball, fan, two-balls, and the paper's
  ball-away, ball-toward (5 ms), diagonal-board, newspaper-board (300 ms), fan-1ms
examples:
  lightflow demo                                    # fan before a wall, 36 frames
  lightflow demo --scene ball --rig single-projector --frames 12
  lightflow demo --scale 1 --frames 6 --out out/    # full resolution, slower per frame"""


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
    p.add_argument("--frames", type=int, default=36, metavar="N",
                   help="frames to render (default 36: 1.2 s of motion at 30 fps)")
    p.add_argument("--scale", type=float, default=0.25, metavar="S",
                   help="camera resolution relative to the rig's (default 0.25: 400x300)")
    p.add_argument("--out", default="out", metavar="DIR",
                   help="where demo.rrd goes (default out/)")
    p.add_argument("--no-viewer", action="store_true",
                   help="only write OUT/demo.rrd, even when a display is available")
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
    """A RerunSink on a spawned viewer (also saving OUT/demo.rrd) or on OUT/demo.rrd only."""
    from lightflow.app.sinks.rerun_sink import RerunSink

    if want_viewer and (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        try:
            out.mkdir(parents=True, exist_ok=True)
            return RerunSink(rig, "spawn", compress=True, save_path=out / "demo.rrd"), True
        except DriverError as exc:
            print(f"note: no Rerun viewer ({exc}); writing a file instead", file=sys.stderr)
    return RerunSink(rig, "rrd", path=out / "demo.rrd", compress=True), False


def warm_up(rig, scene) -> None:
    """Compile the renderer on a tiny image first, saying so (cached after the first run)."""
    from lightflow.drivers.synthetic import SceneRenderer

    print("compiling the renderer (first run only, then cached) ...", end=" ", flush=True)
    t = time.perf_counter()
    tiny = SceneRenderer(rig.scaled(16 / rig.camera.width), scene)
    tiny.radiance(0.0, scene.exposure_s)
    tiny.truth(0.0)
    print(f"{time.perf_counter() - t:.1f} s", flush=True)


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
    warm_up(rig, scene)
    print("rendering and reconstructing (each frame is simulated with motion blur; the first "
          "frame also compiles the depth pipeline on a first run) ...", flush=True)
    status = StatusLine(total=args.frames)
    runner = Runner(camera, pipeline, sinks, on_stats=status, lossless=True)
    with camera:
        stats = runner.run(threading.Event())
    status.finish(stats)
    print(accuracy.describe())
    print(rerun_sink.describe())
    # the viewer comes with rerun-sdk, next to this interpreter (.venv/bin)
    viewer = shutil.which("rerun") or str(Path(sys.executable).parent / "rerun")
    print(f"{'saved as' if spawned else 'open it with'}:  {viewer} {out / 'demo.rrd'}")
    return 130 if runner.interrupted else 0
