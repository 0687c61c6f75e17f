"""``lightflow demo``: render a synthetic moving scene, reconstruct it, show or save it."""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from lightflow.app.core.errors import ConfigError, DriverError
from lightflow.app.status import is_terminal

HELP = "render a moving scene, reconstruct its depth and show it (no hardware needed)"


DESCRIPTION = """\
Render a built-in moving scene as the camera of a rig would see it (projected
line patterns blurred by the motion, with sensor noise), reconstruct its depth
with the same pipeline as `lightflow capture`, and compare with the ground
truth.  Frames stream: each frame is reconstructed and shown while the next
ones render.  The default scene is a ball thrown in front of a static wall:
the ball's blurred lines give depth, the wall's sharp lines are rejected.

With a display the results open in a Rerun viewer; the run is always kept in
OUT/demo.rrd as well (open it later with `rerun OUT/demo.rrd`) unless
--no-save.  The default is 800x600 (--scale 0.5) to keep the demo short.

A first run on a machine also builds the band profile tables (in a helper
process) and the rig's depth table, and compiles the pipeline's and the
renderer's kernels (numba); all of it is cached under $XDG_CACHE_HOME/lightflow
and each step says what it is doing.  Measured with the defaults on a shared
2-core machine (load average 5-9 from other jobs): warm caches, first depth
picture after 6 s and the whole demo in 77 s (56 s of CPU time); empty
caches, first depth picture after 50-90 s (60-80 s of CPU time, most of it
compiling the pipeline's kernels) and the whole demo in 110-155 s.  Rendering
is the bound while streaming (1-2 s a frame at 800x600 under that load); the
first and last lines give the times and the CPU time of the run."""

EPILOG = """\
scenes: ball-wall, board, textured-board, tilted-board, ball, fan, two-balls, and the
  paper's ball-away, ball-toward (5 ms), diagonal-board, newspaper-board (300 ms), fan-1ms
examples:
  lightflow demo                                    # ball in front of a wall, 36 frames
  lightflow demo --scene fan --frames 30
  lightflow demo --scale 1 --frames 10 --out out/   # full 1600x1200, slower per frame"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "demo",
        help=HELP,
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--scene", default="ball-wall", help="built-in scene (default ball-wall)")
    p.add_argument("--rig", default="two-projector", metavar="NAME|PATH",
                   help="two-projector, single-projector or a rig file (default two-projector)")
    p.add_argument("--frames", type=int, default=36, metavar="N",
                   help="frames to render (default 36: 1.5 s of motion at 24 fps)")
    p.add_argument("--scale", type=float, default=0.5, metavar="S",
                   help="camera resolution relative to the rig's (default 0.5: 800x600)")
    p.add_argument("--out", default="out", metavar="DIR",
                   help="where demo.rrd is kept (default out/)")
    p.add_argument("--no-viewer", action="store_true",
                   help="do not open a viewer even when a display is available")
    p.add_argument("--no-save", action="store_true",
                   help="do not keep OUT/demo.rrd (needs a viewer to show anything)")
    p.add_argument("--fps", type=float, default=24.0, help="frame rate of the scene (default 24)")
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


def open_viewer_or_file(rig, out: Path, want_viewer: bool, save: bool = True):
    """A RerunSink on a spawned viewer when a display allows it, else on OUT/demo.rrd.

    With ``save`` the run is kept in OUT/demo.rrd also when a viewer opens.
    Returns the sink and whether a viewer was spawned.
    """
    from lightflow.app.sinks.rerun_sink import RerunSink

    path = out / "demo.rrd"
    if want_viewer and (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        try:
            return RerunSink(rig, "spawn", compress=True, save_path=path if save else None), True
        except DriverError as exc:
            print(f"note: no Rerun viewer ({exc}); writing a file instead", file=sys.stderr)
    if not save:
        raise ConfigError("--no-save: no viewer can open here, so nothing would be shown or kept")
    return RerunSink(rig, "rrd", path=path, compress=True), False


class CompileProgress:
    """Says which numba kernel is being compiled, and for how long, while a block runs.

    On a terminal one line is rewritten in place twice a second; otherwise only
    the summary is printed.  Uses numba's event API (``numba:compile`` events).
    """

    def __init__(self, label: str, stream=None):
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.tty = is_terminal(self.stream)
        self.kernels = 0
        self.current = ""
        self._depth = 0
        self._done = threading.Event()
        self._listener = None

    def _on_start(self, event) -> None:
        self._depth += 1
        if self._depth == 1:
            self.kernels += 1
            self.current = event.data["dispatcher"].py_func.__name__

    def _on_end(self, event) -> None:
        self._depth -= 1

    def _tick(self) -> None:
        # a display refresh, not a poll: the wait ends at once when the block does
        while not self._done.wait(0.5):
            if self.current:
                elapsed = time.perf_counter() - self.t0
                self.stream.write(f"\r{self.label}: compiling {self.current:<24s} "
                                  f"(kernel {self.kernels}, {elapsed:5.1f} s)")  # fmt: skip
                self.stream.flush()

    def __enter__(self) -> CompileProgress:
        from numba.core import event

        owner = self

        class Listener(event.Listener):
            def on_start(self, ev) -> None:
                owner._on_start(ev)

            def on_end(self, ev) -> None:
                owner._on_end(ev)

        self._listener = Listener()
        event.register("numba:compile", self._listener)
        self.t0 = time.perf_counter()
        if self.tty:
            self._ticker = threading.Thread(target=self._tick, daemon=True)
            self._ticker.start()
        return self

    def __exit__(self, *exc) -> None:
        from numba.core import event

        self._done.set()
        if self.tty:
            self._ticker.join()
            self.stream.write("\r" + " " * 78 + "\r")
        event.unregister("numba:compile", self._listener)
        self.seconds = time.perf_counter() - self.t0

    def summary(self) -> str:
        if not self.kernels:
            return "kernels loaded from numba's cache"
        return f"compiled {self.kernels} kernels (numba; cached for the next runs)"


def cpu_seconds() -> float:
    """CPU time of this process and its finished helpers (user + system), in seconds."""
    import resource

    own = resource.getrusage(resource.RUSAGE_SELF)
    helpers = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + helpers.ru_utime + helpers.ru_stime


def render_ahead(camera, helper, done: threading.Event, failed: list, since) -> None:
    """Render frames ahead on one idle-priority thread until ``done`` is set or the scene ends.

    Waits for the helper process first (it compiles the renderer's kernels
    into numba's cache, and this process is busy compiling the pipeline's).
    The thread runs at the lowest priority: it uses a core that compilation
    leaves idle and must not slow the compilation down.  An exception is
    appended to ``failed`` for the caller to raise.
    """
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)  # this thread only
        if helper is not None:
            helper.wait()
            if helper.returncode != 0:
                return  # the main thread compiles the renderer after the pipeline
            print(f"\n      helper: profile tables and renderer kernels ready after {since()}",
                  flush=True)  # fmt: skip
        while not done.is_set() and camera.render_ahead(1, threads=1):
            pass
    except BaseException as exc:  # noqa: BLE001 - handed to the main thread
        failed.append(exc)


def renderer_cached() -> bool:
    """Whether numba's on-disk cache holds the renderer's main kernel."""
    from lightflow.drivers.sim import render

    pattern = "render.render_exposure_fast-*.nbi"
    root = os.environ.get("NUMBA_CACHE_DIR")
    if root:
        return any(Path(root).rglob(pattern))
    return any((Path(render.__file__).parent / "__pycache__").glob(pattern))


#: the helper process: profile tables, then the renderer's kernels (argv: rig, scene)
HELPER = (
    "import sys\n"
    "from lightflow.app.core.profile_model import tables\n"
    "from lightflow.app.core.rig import resolve_rig\n"
    "from lightflow.drivers.sim.synthetic import warm_up_renderer\n"
    "tables()\n"
    "warm_up_renderer(resolve_rig(sys.argv[1]), sys.argv[2])\n"
)


def get_scene_checked(name: str):
    """The built-in scene ``name`` (ConfigError naming the choices otherwise)."""
    from lightflow.drivers.sim.scenes import get_scene

    return get_scene(name)


def run(args: argparse.Namespace) -> int:
    from lightflow.app.core.depth_model import load_or_build_lut
    from lightflow.app.core.pipeline import DepthPipeline
    from lightflow.app.core.profile_model import prefetch_tables, tables_path
    from lightflow.app.core.rig import resolve_rig
    from lightflow.app.options import close_all, pipeline_config
    from lightflow.app.runner import Runner
    from lightflow.app.status import Progress, StatusLine
    from lightflow.drivers.sim.synthetic import SyntheticCamera

    start = time.perf_counter()

    def since() -> str:
        return f"{time.perf_counter() - start:.1f} s"

    if args.frames <= 0:
        raise ConfigError(f"--frames: expected a positive number, got {args.frames}")
    if not 0.05 <= args.scale <= 2:
        raise ConfigError(f"--scale: expected 0.05 .. 2, got {args.scale}")
    display = bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    if args.no_save and (args.no_viewer or not display):
        raise ConfigError("--no-save: no viewer will open here, so nothing would be shown or kept")
    scene = get_scene_checked(args.scene)
    rig = resolve_rig(args.rig)
    if args.scale != 1:
        rig = rig.scaled(args.scale)
    cam = rig.camera
    config = pipeline_config(args)
    print(f"demo: scene {scene.name} ({scene.description}), {cam.width}x{cam.height} camera"
          f"{f' (--scale {args.scale:g})' if args.scale != 1 else ''}, "
          f"{len(rig.projectors)} projector(s), {args.frames} frames at {args.fps:g} fps "
          f"({args.frames / args.fps:.1f} s of motion)", flush=True)
    # A first run on a machine builds tables and compiles kernels (numba, one
    # core each), all cached.  The pipeline's kernels take longest: this process
    # compiles them at once, while a helper process builds the profile tables
    # (which the pipeline needs only half-way through) and then compiles the
    # renderer; frames are rendered ahead on the core left idle.
    helper = None
    if tables_path().exists() and renderer_cached():
        print("[1/4] band profile tables and renderer kernels: found in the cache", flush=True)
    else:
        print("[1/4] helper process: the band profile tables (what the band detector reports "
              "for every sweep, line width and blur), then the renderer's kernels; once per "
              "machine ...", flush=True)  # fmt: skip
        helper = subprocess.Popen(
            [sys.executable, "-c", HELPER, str(args.rig), scene.name],
            stdout=subprocess.DEVNULL,
        )  # fmt: skip
    camera = SyntheticCamera(rig, scene.name, frames=args.frames, fps=args.fps)
    done = threading.Event()
    failed: list[BaseException] = []
    ahead = threading.Thread(target=render_ahead, args=(camera, helper, done, failed, since),
                             name="render-ahead")  # fmt: skip
    try:
        print("[2/4] depth table of this rig (once per rig) ...", flush=True)
        lut = load_or_build_lut(rig, config.stride, config.depth_range,
                                Progress("      building the depth table"))  # fmt: skip
        print(f"      ready after {since()}", flush=True)
        print("[3/4] depth pipeline: its kernels, on a test image"
              + (" (it waits for the profile tables half-way)" if helper else "") + " ...",
              flush=True)  # fmt: skip
        prefetch_tables()  # the pipeline needs them only once its band kernels are compiled
        ahead.start()
        with CompileProgress("      pipeline") as compiling:
            try:
                pipeline = DepthPipeline(rig, config, lut=lut)
                pipeline.warm_up()
            finally:
                done.set()
                ahead.join()
        if failed:
            raise failed[0]
        print(f"      {compiling.summary()}; ready after {since()}", flush=True)
        n = camera.frames_ahead
        print("[4/4] renderer: " + (f"{n} frame{'s' if n > 1 else ''} rendered meanwhile" if n
              else "the first frame ..."), flush=True)  # fmt: skip
        if not camera.frames_ahead:
            with CompileProgress("      renderer") as compiling:
                camera.render_ahead(1)
            print(f"      {compiling.summary()}; frame 1 rendered after {since()}", flush=True)
    except BaseException:
        camera.close()
        raise
    finally:
        if helper is not None and helper.poll() is None:
            helper.kill()
            helper.wait()
    out = Path(args.out)
    try:
        rerun_sink, spawned = open_viewer_or_file(rig, out, not args.no_viewer, not args.no_save)
    except BaseException:
        camera.close()
        raise
    accuracy = AccuracySink(len(rig.projectors))
    sinks = [rerun_sink, accuracy]
    print(f"streaming after {since()}: each frame is rendered with motion blur, then "
          "reconstructed and logged while the next ones render", flush=True)
    first = {}

    class FirstDepth:
        """Notes when the first depth picture is logged."""

        def write(self, result, stats) -> None:
            if "t" not in first:
                first["t"] = time.perf_counter() - start
                print(f"\nfirst depth picture after {first['t']:.1f} s ({cpu_seconds():.0f} s "
                      "of CPU time, helper included)", flush=True)  # fmt: skip

        def close(self) -> None:
            """Nothing to flush."""

    sinks.append(FirstDepth())
    status = StatusLine(total=args.frames)
    try:
        runner = Runner(camera, pipeline, sinks, on_stats=status, lossless=True)
    except BaseException:
        close_all(sinks)
        camera.close()
        raise
    with camera:
        stats = runner.run(threading.Event())
    status.finish(stats)
    print(accuracy.describe())
    print(rerun_sink.describe())
    print(f"demo took {time.perf_counter() - start:.1f} s ({cpu_seconds():.0f} s of CPU time; "
          f"load average {os.getloadavg()[0]:.1f})")
    if not args.no_save:
        # the viewer comes with rerun-sdk, next to this interpreter (.venv/bin)
        viewer = shutil.which("rerun") or str(Path(sys.executable).parent / "rerun")
        print(f"open it with:  {viewer} {out / 'demo.rrd'}")
    return 130 if runner.interrupted else 0
