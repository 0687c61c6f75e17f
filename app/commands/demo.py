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
ones render.  The default scene shows two boards moving in depth in opposite
directions (0.6-0.9 m, 0.6 m/s) in front of a static wall at 1.1 m, exposed
30 ms: the boards' blurred lines give depth, the wall's sharp lines are
rejected (cause "static").

At the end the demo prints how many frames got depth on the moving objects,
the median error against the ground truth and the coverage: of the pixels on
a moving object that every projector lights, the share that got a depth (the
one definition used by `lightflow eval` and Rerun's green series; the status
line's "depth on image" is the share of all camera pixels).  With the
defaults: 36 of 36 frames with depth, median error 0.1 mm (90th percentile
0.2 mm), coverage 92 % (left board 96 %, right board 87 %).

The colour leak between the red and blue pattern channels is the simulated
camera's, per pattern (red sees 4 % of the blue light, blue 3 % of the red),
as `lightflow rig blur` would measure it; --crosstalk auto estimates it from
the frames, as capture does without a measured rig, and a number gives both
patterns that leak.  With a display the results open in a Rerun viewer; the
run is always kept in OUT/demo.rrd as well (open it later with `rerun
OUT/demo.rrd`) unless --no-save.  The default is 800x600 (--scale 0.5) to keep the demo short.

A first run on a machine also builds the band profile tables (from the band
detector's measurements shipped with the sources) and the rig's depth table
and compiles the pipeline's and the renderer's kernels (numba), in this
process and a helper process side by side; all of it is cached under
$XDG_CACHE_HOME/lightflow and each step says what it is doing.  Measured with
the defaults on a shared 2-core machine (tests/bench_demo.py, empty caches,
load average 1.3-2.2): first depth picture after 21-22 s (42-44 s of CPU
time, more under load) and the whole demo in 58-60 s.  Rendering is the bound
while streaming (about 1.5 s of CPU time per frame); the first and last lines
give the times and the CPU time of the run."""

EPILOG = """\
scenes: boards-wall (default), ball-wall, board, textured-board, tilted-board, ball, fan,
  two-balls, and the paper's ball-away, ball-toward (5 ms), diagonal-board,
  newspaper-board (300 ms), fan-1ms
examples:
  lightflow demo                                    # two boards before a wall, 36 frames
  lightflow demo --scene ball-wall --crosstalk auto
  lightflow demo --scale 1 --frames 10 --out out/   # full 1600x1200, slower per frame"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "demo",
        help=HELP,
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--scene", default="boards-wall",
                   help="built-in scene (default boards-wall)")
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
    p.add_argument("--crosstalk", metavar="auto|LEAK",
                   help="colour leak between the pattern channels: auto estimates it from the "
                        "frames, as capture does; a number gives both patterns that leak (default: "
                        "the simulated camera's, 0.04 and 0.03)")
    p.set_defaults(func=run, stride=4, smoothing=None)


class AccuracySink:
    """Scores each depth map against the renderer's ground truth, as ``lightflow eval`` does.

    Coverage is the one definition of :mod:`lightflow.app.evaluation` (also in
    eval and Rerun): of the pixels on a moving object (object id >= 2) that
    every projector lights, the share that got a depth.  Static surfaces leave
    no blur, so no depth is expected there.  Also counts the frames with depth
    on the moving objects and the coverage of each named object.
    """

    def __init__(self, n_projectors: int, objects: tuple = ()):
        self.n_projectors = n_projectors
        self.objects = objects
        self.per_frame: list = []
        #: per object id, [target pixels, covered pixels] over the run
        self.by_object: dict[int, list[int]] = {}

    def write(self, result, stats) -> None:
        from lightflow.app.evaluation import evaluate_frame

        truth = result.frame.extras.get("truth")
        if truth is None:
            return
        self.per_frame.append(evaluate_frame(result.depth, truth, n_projectors=self.n_projectors))
        if len(self.objects) > 1:
            for obj in range(2, 2 + len(self.objects)):
                # the same definition, scoring one object: the others count as static
                ids = np.where((truth.object_id >= 2) & (truth.object_id != obj), 1,
                               truth.object_id).astype(truth.object_id.dtype)  # fmt: skip
                one = type(truth)(truth.depth, ids, truth.lit, truth.planar)
                m = evaluate_frame(result.depth, one, n_projectors=self.n_projectors)
                acc = self.by_object.setdefault(obj, [0, 0])
                acc[0] += m.n_target
                acc[1] += m.n_covered

    def close(self) -> None:
        """Nothing to flush."""

    @property
    def frames_with_depth(self) -> int:
        """Frames in which a moving object got at least one depth."""
        return sum(1 for m in self.per_frame if m.n_covered > 0)

    def describe(self) -> list[str]:
        """The accuracy lines printed at the end of the demo."""
        from lightflow.app.evaluation import pool_metrics

        n = len(self.per_frame)
        seen = [m for m in self.per_frame if m.n_target > 0]
        if not seen:
            return [f"accuracy: no moving object was lit in these {n} frames"]
        p = pool_metrics(self.per_frame)
        lines = [f"frames with depth on the moving objects: {self.frames_with_depth} of {n} "
                 f"({sum(1 for m in seen if m.coverage >= 0.1)} with at least 10 % coverage)"]
        if not self.frames_with_depth:
            return lines + ["accuracy: no depth on the moving objects (coverage 0 %)"]
        parts = []
        for obj, name in enumerate(self.objects, 2):
            target, covered = self.by_object.get(obj, (0, 0))
            if target:
                parts.append(f"{name} {100 * covered / target:.0f} %")
        lines.append(
            f"accuracy against ground truth: median error {p['median_error_m'] * 1e3:.1f} mm "
            f"(90th percentile {p['p90_error_m'] * 1e3:.1f} mm, median signed "
            f"{p['median_signed_m'] * 1e3:+.1f} mm); coverage {100 * p['coverage']:.0f} %"
            + (f" ({', '.join(parts)})" if parts else "")
        )
        lines.append("  (coverage: of the moving objects' pixels that every projector lights, "
                     "the share with a depth, as in `lightflow eval` and Rerun)")
        return lines


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


class Helper:
    """The helper process: half of the band detector's kernels, the tables, the renderer.

    Last, the kernels of the arcs' line intervals, of the triangulated depth and of
    overlapping bands (:func:`lightflow.app.core.arcs.warm_up`,
    :func:`lightflow.app.core.triangulation.warm_up`, :func:`lightflow.app.core.overlap.warm_up`),
    which this process would otherwise compile at the end of the pipeline's warm-up.  This
    process compiles meanwhile the kernels of the depth from the line intervals
    (:func:`lightflow.app.core.intervals.warm_up`) and of the grid rows the arcs change
    (:func:`lightflow.app.core.pipeline.warm_up_kernels`): both end at about the same time.

    It compiles the detector's ``sliding_mid`` while this process compiles
    ``bands_in_row`` (numba's on-disk cache hands each to the other process),
    then builds the band profile tables (from the detector's measurements
    shipped with the sources; without them it runs the detector on every cell,
    once this process says (:meth:`go`) that its row kernel is cached), then the
    rig's depth table, then compiles the renderer.  This process meanwhile
    compiles the rest of the band stage and, once the two tables are cached,
    the rest of the pipeline: about equal shares of CPU time.  Whatever is
    cached is loaded.  Its steps arrive as lines on its stdout (read by a
    thread: no polling).
    """

    #: argv: rig, scale, stride, near, far, scene, "wait" (for a line on stdin before
    #: the tables) or "go"
    SCRIPT = (
        "import sys\n"
        "import numpy as np\n"
        "from lightflow.app.core import bands\n"
        "rig, scale, stride, near, far, scene, wait = sys.argv[1:]\n"
        "bands.sliding_mid(np.zeros(64), 5, np.zeros((2, 64)))\n"
        "print('sliding_mid', flush=True)\n"
        "from lightflow.app.core.profile_model import tables\n"
        "if wait == 'wait':\n"
        "    sys.stdin.readline()\n"
        "tables()\n"
        "print('tables', flush=True)\n"
        "from lightflow.app.core.depth_model import DepthRange, load_or_build_lut\n"
        "from lightflow.app.core.rig import resolve_rig\n"
        "r = resolve_rig(rig)\n"
        "r = r if float(scale) == 1 else r.scaled(float(scale))\n"
        "load_or_build_lut(r, int(stride), DepthRange(float(near), float(far)))\n"
        "print('lut', flush=True)\n"
        "from lightflow.drivers.sim.synthetic import warm_up_renderer\n"
        "warm_up_renderer(resolve_rig(rig), scene)\n"
        "print('renderer', flush=True)\n"
        "from lightflow.app.core import arcs, overlap, triangulation\n"
        "arcs.warm_up()\n"
        "triangulation.warm_up()\n"
        "overlap.warm_up()\n"
        "print('overlap', flush=True)\n"
    )

    def __init__(self, argv: list[str], since, on_renderer=None):
        self.since = since
        self.on_renderer = on_renderer
        self.sliding_mid = threading.Event()
        self.renderer = threading.Event()
        self.tables = threading.Event()
        self.lut = threading.Event()
        self.overlap = threading.Event()
        self.proc = subprocess.Popen(
            [sys.executable, "-c", self.SCRIPT, *argv],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        )  # fmt: skip
        self._reader = threading.Thread(target=self._read, name="demo-helper", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            step = line.strip()
            if step == "sliding_mid":
                self.sliding_mid.set()
            elif step == "renderer":
                print(f"\n      helper: renderer kernels ready after {self.since()}", flush=True)
                self.renderer.set()
                if self.on_renderer is not None:
                    self.on_renderer()
            elif step == "tables":
                print(f"\n      helper: band profile tables ready after {self.since()}",
                      flush=True)  # fmt: skip
                self.tables.set()
            elif step == "lut":
                print(f"\n      helper: depth table ready after {self.since()}", flush=True)
                self.lut.set()
            elif step == "overlap":
                print(f"\n      helper: overlapping-band kernels ready after {self.since()}",
                      flush=True)  # fmt: skip
                self.overlap.set()
        self.proc.stdout.close()
        self.proc.wait()
        # wake whoever waits: a failed helper leaves its steps to this process
        for step in (self.sliding_mid, self.renderer, self.tables, self.lut, self.overlap):
            step.set()
        if self.on_renderer is not None:
            self.on_renderer()

    @property
    def failed(self) -> bool:
        """Whether the helper ended with an error."""
        return self.proc.returncode not in (None, 0)

    def go(self) -> None:
        """Tell the helper that this process's row kernel is cached: build the tables now."""
        try:
            self.proc.stdin.write("go\n")
            self.proc.stdin.close()
        except OSError:  # it has already ended; what it left undone is done here
            pass

    def close(self) -> None:
        """Stop the helper if it still runs (what it built so far is cached)."""
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()
        self._reader.join()
        try:
            self.proc.stdin.close()
        except OSError:  # "go" still buffered for a helper that had ended
            pass


def render_ahead(camera, helper: Helper | None, wake: threading.Event, done: threading.Event,
                 failed: list) -> None:  # fmt: skip
    """Render frames ahead on one idle-priority thread until ``done`` is set or the scene ends.

    With a helper, waits for ``wake`` first: set when the helper has compiled
    the renderer's kernels into numba's cache (this process is busy compiling
    the pipeline's) or has ended, and with ``done``.  The
    thread runs at the lowest priority: it uses a core that compilation
    leaves idle and must not slow the compilation down.  An exception is
    appended to ``failed`` for the caller to raise.
    """
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)  # this thread only
        if helper is not None:
            wake.wait()
            if done.is_set() or helper.failed:
                return  # the main thread compiles the renderer after the pipeline
        # the first frame on every core: it is on the way to the first depth picture,
        # which waits for it once the pipeline is ready (the helper has ended by now)
        threads = None if camera.frames_ahead == 0 else 1
        while not done.is_set() and camera.render_ahead(1, threads=threads):
            threads = 1
    except BaseException as exc:  # noqa: BLE001 - handed to the main thread
        failed.append(exc)


def in_numba_cache(module, *names: str) -> bool:
    """Whether numba's on-disk cache holds a kernel of each name of ``module``."""
    root = os.environ.get("NUMBA_CACHE_DIR")
    short = module.__name__.rsplit(".", 1)[-1]
    folders = [Path(root)] if root else [Path(module.__file__).parent / "__pycache__"]
    for name in names:
        pattern = f"{short}.{name}-*.nbi"
        if not any(any(f.rglob(pattern)) for f in folders if f.is_dir()):
            return False
    return True


class BandStageWarmUp:
    """Compiles the band stage's kernels as the pipeline calls them, on a striped test image.

    :meth:`measure_row` compiles the detector's row kernel, which the helper
    process builds the profile tables with (numba's on-disk cache hands it
    over); :meth:`detect` the rest of the detector and :meth:`rasterise` the
    slants and the rasterisation onto the analysis grid, meanwhile.  Argument types follow
    :class:`~lightflow.app.core.pipeline.DepthPipeline`: a mismatch would only
    compile a kernel once more.
    """

    def __init__(self, rig, config):
        from lightflow.app.core import bands as bd
        from lightflow.app.core.pipeline import MAX_BANDS_PER_ROW

        cam = rig.camera
        x = np.arange(cam.width)
        self.image = np.full((cam.height, cam.width, 3), 20, np.uint8)
        self.image[:, (x % 40) < 14, 0] = 200  # red lines, a 40 px interval
        self.image[:, (x % 18) < 7, 2] = 200  # blue lines, an 18 px interval
        b = config.bands
        self.params = np.array([b.min_contrast, b.interval_tolerance, b.symmetry_tolerance_px,
                                b.min_gap_px, b.vertical_extra], dtype=np.float64)  # fmt: skip
        self.stride = s = config.stride
        self.group = max(1, min(b.rows_per_cell, s))  # measured rows per grid cell
        self.row_y = (np.arange(cam.height // s)[:, None] * s + (s - self.group) // 2
                      + np.arange(self.group)[None, :]).ravel().astype(np.int64)  # fmt: skip
        self.cells = (cam.height // s, cam.width // s)
        self.bands = np.empty((2, len(self.row_y), MAX_BANDS_PER_ROW, bd.N_FIELDS))
        self.counts = np.empty((2, len(self.row_y)), np.int64)

    def measure_row(self) -> None:
        """Compile (or load) ``bands_in_row``, the detector's measurement of one row."""
        from lightflow.app.core import bands as bd

        w = self.image.shape[1]
        out = np.empty((self.bands.shape[2], self.bands.shape[3]))
        bd.bands_in_row(np.zeros(w), np.zeros((2, w)), 6.0, 0.3, 1.0, 0.25, np.zeros(3), out)

    def detect(self) -> None:
        """Compile (or load) the band detector's kernels."""
        from lightflow.app.core import bands as bd

        weights = np.zeros((2, 3))
        weights[0, 0] = weights[1, 2] = 1.0
        bd.detect_bands(self.image, weights, self.row_y, np.array([61, 61]), 255.0, self.params,
                        np.zeros((2, 3)), self.bands, self.counts, self.group)  # fmt: skip

    def rasterise(self) -> None:
        """Compile (or load) the band slants and the rasterisation onto the grid."""
        from lightflow.app.core import bands as bd

        fields = np.array(bd.GRID_FIELDS, dtype=np.int64)
        gh, gw = self.cells
        grids = np.empty((2, len(fields), gh, gw))
        for p in range(2):
            bd.band_slants(self.bands[p], self.counts[p], self.row_y)
            bd.rasterise_cells(self.bands[p], self.counts[p], self.group, self.stride, gw, 0.5,
                               fields, grids[p])  # fmt: skip


def simulated_crosstalk(rig) -> list[float]:
    """Per pattern (file order), the colour crosstalk of the simulated camera.

    The share of the other pattern's light that each pattern's camera channel sees
    (:class:`~lightflow.drivers.sim.synthetic.SensorModel`'s crosstalk, camera channel by
    light colour): what ``lightflow rig blur`` would measure on still lines, known here
    because the demo's camera is simulated.  Red and blue see each other differently
    (4 % and 3 %), so each pattern gets its own.
    """
    from lightflow.app.core.rig import CHANNEL_INDEX
    from lightflow.drivers.sim.synthetic import SensorModel

    xt = np.asarray(SensorModel().crosstalk)
    channels = [CHANNEL_INDEX[pat.channel] for _, pat in rig.patterns]
    if len(channels) != 2:
        return [0.0] * len(channels)
    a, b = channels
    return [round(float(xt[a, b]), 4), round(float(xt[b, a]), 4)]


def get_scene_checked(name: str):
    """The built-in scene ``name`` (ConfigError naming the choices otherwise)."""
    from lightflow.drivers.sim.scenes import get_scene

    return get_scene(name)


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from lightflow.app.core import bands as bd
    from lightflow.app.core import intervals
    from lightflow.app.core.depth_model import load_or_build_lut
    from lightflow.app.core.flow import warm_up_reread
    from lightflow.app.core.pipeline import DepthPipeline, warm_up_kernels
    from lightflow.app.core.profile_model import MEASURED_PATH, prefetch_tables, tables_path
    from lightflow.app.core.rig import resolve_rig
    from lightflow.app.options import close_all, pipeline_config
    from lightflow.app.runner import Runner
    from lightflow.app.status import Progress, StatusLine
    from lightflow.drivers.sim import render
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
    if args.crosstalk == "auto":
        crosstalk, leak_text = "auto", "estimated from the frames (--crosstalk auto)"
    elif args.crosstalk is None:
        # the simulated camera's, per pattern, as `lightflow rig blur` would put it in the rig
        leaks = simulated_crosstalk(rig)
        rig = rig.with_crosstalk(leaks)
        crosstalk = "auto"  # the rig's own
        leak_text = (" and ".join(f"{v:g}" for v in leaks) + " (the simulated camera's, per "
                     "pattern)")  # fmt: skip
    else:
        crosstalk = parse_leak(args.crosstalk)
        leak_text = f"{crosstalk:g}"
    config = replace(pipeline_config(args), crosstalk=crosstalk)
    print(f"demo: scene {scene.name} ({scene.description}), {cam.width}x{cam.height} camera"
          f"{f' (--scale {args.scale:g})' if args.scale != 1 else ''}, "
          f"{len(rig.projectors)} projector(s), {args.frames} frames at {args.fps:g} fps "
          f"({args.frames / args.fps:.1f} s of motion), exposure {scene.exposure_s * 1e3:g} ms, "
          f"colour leak {leak_text}", flush=True)  # fmt: skip
    # A first run on a machine builds tables and compiles kernels (numba, one core
    # each), all cached.  This process and a helper process compile the band
    # detector's two row kernels side by side; the helper then builds the band profile
    # tables (from the shipped measurements) and the depth table while this process
    # compiles the rest of the band stage, then compiles the renderer while this
    # process compiles the rest of the pipeline (which needs both tables).  The first
    # frame renders on every core once the renderer is cached, the next ones ahead on
    # whatever core is left idle.
    helper = None
    done = threading.Event()  # stops the rendering ahead
    wake = threading.Event()  # the renderer's kernels are cached, or stop waiting for them
    need_tables = not tables_path().exists()
    if need_tables or not in_numba_cache(render, "render_exposure_fast", "knot_states"):
        print("[1/4] helper process: half of the band detector's kernels, the band profile tables "
              "(what the band detector reports for every sweep, line width and blur), the rig's "
              "depth table, then the renderer's kernels; once per machine ...",
              flush=True)  # fmt: skip
        # the tables run the detector's row kernels only without the shipped measurements
        wait = need_tables and not MEASURED_PATH.exists()
        helper = Helper([str(args.rig), str(args.scale), str(config.stride),
                         str(config.depth_range.near), str(config.depth_range.far), scene.name,
                         "wait" if wait else "go"], since,
                        on_renderer=wake.set)  # fmt: skip
    else:
        print("[1/4] band profile tables and renderer kernels: found in the cache", flush=True)
    camera = SyntheticCamera(rig, scene.name, frames=args.frames, fps=args.fps)
    failed: list[BaseException] = []
    ahead = threading.Thread(target=render_ahead, args=(camera, helper, wake, done, failed),
                             name="render-ahead")  # fmt: skip
    try:
        ahead.start()
        cached = in_numba_cache(bd, "bands_in_row", "sliding_mid")
        print("[2/4] band detector and rasterisation: "
              + ("their kernels are in the cache" if cached else "their kernels, on a test image"
                 + (" (the helper builds the profile tables with the row kernels)" if need_tables
                    else "") + " ..."), flush=True)  # fmt: skip
        band_stage = BandStageWarmUp(rig, config)
        with CompileProgress("      band detector") as compiling:
            try:
                band_stage.measure_row()
            finally:
                if helper is not None:
                    helper.go()
            if helper is not None:
                helper.sliding_mid.wait()  # compiled there meanwhile (or left to this process)
            band_stage.detect()
            band_stage.rasterise()
        print(f"      {compiling.summary()}; ready after {since()}", flush=True)
        print("[3/4] depth table of this rig (once per rig"
              + ("; the helper builds it" if helper is not None else "") + ") ...", flush=True)
        if helper is not None:
            helper.lut.wait()  # then loaded from the cache (built here if the helper failed)
        lut = load_or_build_lut(rig, config.stride, config.depth_range,
                                Progress("      building the depth table"))  # fmt: skip
        print(f"      ready after {since()}", flush=True)
        print("[4/4] depth pipeline: its other kernels, on a test image"
              + (" (after the helper's profile tables)" if need_tables else "") + " ...",
              flush=True)  # fmt: skip
        if helper is not None:
            # one process builds the tables; a failed helper leaves them to this one
            helper.tables.wait()
        prefetch_tables()
        with CompileProgress("      pipeline") as compiling:
            try:
                pipeline = DepthPipeline(rig, config, lut=lut)
                pipeline.warm_up(optional=helper is None)
                if helper is not None:
                    # the second reading's and the interval depth's kernels here: the helper
                    # has more left to compile
                    warm_up_reread()
                    warm_up_kernels()
                    intervals.warm_up()
                    helper.overlap.wait()  # compiled there meanwhile: loaded from the cache
                    pipeline.warm_up_optional()
            finally:
                done.set()
                wake.set()
                ahead.join()
        if failed:
            raise failed[0]
        print(f"      {compiling.summary()}; ready after {since()}", flush=True)
        n = camera.frames_ahead
        print("      renderer: " + (f"{n} frame{'s' if n > 1 else ''} rendered meanwhile" if n
              else "the first frame ..."), flush=True)  # fmt: skip
        if helper is not None and not helper.renderer.is_set():
            print("      (the helper is still compiling the renderer's kernels)", flush=True)
            helper.renderer.wait()  # set also when it ends: then this process compiles them
        if not camera.frames_ahead:
            with CompileProgress("      renderer") as compiling:
                camera.render_ahead(1)
            print(f"      {compiling.summary()}; frame 1 rendered after {since()}", flush=True)
    except BaseException:
        done.set()
        wake.set()
        if ahead.is_alive():
            ahead.join()
        camera.close()
        raise
    finally:
        if helper is not None:
            helper.close()
    out = Path(args.out)
    try:
        rerun_sink, spawned = open_viewer_or_file(rig, out, not args.no_viewer, not args.no_save)
    except BaseException:
        camera.close()
        raise
    accuracy = AccuracySink(len(rig.projectors), scene.objects)
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
    for line in accuracy.describe():
        print(line)
    print(rerun_sink.describe())
    print(f"demo took {time.perf_counter() - start:.1f} s ({cpu_seconds():.0f} s of CPU time; "
          f"load average {os.getloadavg()[0]:.1f})")
    if not args.no_save:
        # the viewer comes with rerun-sdk, next to this interpreter (.venv/bin)
        viewer = shutil.which("rerun") or str(Path(sys.executable).parent / "rerun")
        print(f"open it with:  {viewer} {out / 'demo.rrd'}")
    if runner.closed_output:
        print(f"stopped: {runner.closed_output}")
    return 130 if runner.interrupted else 0


def parse_leak(text: str) -> float:
    """``--crosstalk``'s number (ConfigError otherwise)."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0 <= value < 0.5:
        raise ConfigError(f"--crosstalk: expected auto or a leak of 0 .. 0.5, got {text!r}")
    return value
