"""Rerun sink: camera image with depth, 3D points, bands, flows and readable live stats.

Entity layout (all per frame on the ``frame`` timeline, plus ``camera_time``)::

    world                        ViewCoordinates RDF (static): the camera frame is the world
    world/camera                 Transform3D (identity) + Pinhole (static); 2D entities below
    world/camera/image           RGB image
    world/camera/depth           DepthImage, uint16 mm, fixed colour range (0 = no estimate)
    world/camera/depth_overlay   SegmentationImage: the same colours in 255 steps (hover: the
                                 depth), see-through, drawn over the image
    world/camera/bands/<ch>/accepted|rejected   LineStrips2D, one segment per band;
                                 accepted: passed the checks and kept a flow
    world/points                 Points3D in world space (NOT under the pinhole, which would
                                 hide them in 3D), coloured by depth like the depth image
    flow/<ch>, flow/log_ratio    the light flows in projector px, and their log ratio, as
                                 colour-mapped images with a fixed range (named in the view)
    uncertainty/depth_std        predicted depth standard deviation, colour-mapped 0-30 mm
    causes                       SegmentationImage: per grid pixel, depth or why none (the
                                 annotation context names each cause; hover to read it)
    stats/no_depth               BarChart: % of grid pixels per cause, in cause order
    stats/rate/fps, stats/rate/mib_per_s           rates
    stats/time_ms/latency|processing               milliseconds (the first frame, dominated
                                                   by compilation, is left out of the plot)
    stats/coverage/...           percent: "depth on image" (every run) and, with ground
                                 truth, "moving lit pixels with depth" (eval's coverage)
    stats/lost/...               counts: dropped frames/results, camera losses, counters
    log                          TextLog: what the plots leave out (first-frame timing)


Network: ``serve`` and ``spawn`` run the Rerun binary as a child process bound to
127.0.0.1 only; the SDK's own ``serve_grpc`` has no bind option and listens on
every interface, which would publish camera images to the network.  A server
child dies with lightflow (parent-death signal), even when lightflow is killed.

A full disk while writing an .rrd is one :class:`DriverError` naming the file,
within a second, and the partial file is removed (see :class:`RerunOutput`).
"""

from __future__ import annotations

import collections
import ctypes
import os
import re
import signal
import subprocess
import tempfile
import threading
import time
import uuid
from pathlib import Path

import cv2
import numba as nb
import numpy as np
import pyarrow as pa

from lightflow.app.core.causes import CAUSE_COLOURS, CAUSES
from lightflow.app.core.errors import ConfigError, DriverError, OutputClosed
from lightflow.app.core.geometry import camera_rays
from lightflow.app.core.results import BandSet, FrameResult, RunStats
from lightflow.app.core.rig import Rig
from lightflow.app.core.threads import run_rows
from lightflow.app.evaluation import coverage
from lightflow.app.sinks.ply import depth_to_points, image_to_rgb8
from lightflow.app.sinks.rrd_file import RrdFile

# The SDK's Rust side prints its own multi-line errors when an .rrd write fails; this
# sink reports that failure as one line itself.  Set before the SDK starts its logger;
# a RUST_LOG chosen by the user wins.
_QUIET_SDK = "warn,re_log_encoding=off,re_sdk::recording_stream=off,re_grpc_client=off"
os.environ.setdefault("RUST_LOG", _QUIET_SDK)

import rerun as rr  # noqa: E402
import rerun.blueprint as rrb  # noqa: E402

MODES = ("rrd", "spawn", "serve")
#: display colour of each pattern channel for accepted bands; rejected ones are grey
CHANNEL_RGB = {"red": (255, 64, 64), "green": (64, 255, 64), "blue": (80, 140, 255)}
REJECTED_RGB = (120, 120, 120)
READY_TIMEOUT_S = 30.0
#: default colour range of depth, metres: the rig check's working depths (0.5-1 m) with margin
DEPTH_RANGE_M = (0.4, 1.2)
#: colour range of the log flow ratio (dimensionless)
LOG_RATIO_RANGE = (-1.0, 1.0)
#: colour range of the predicted depth error (mm)
STD_RANGE_MM = 30.0
COLORMAP = "turbo"
#: opacity of the depth colours over the camera image (0-255)
OVERLAY_ALPHA = 170
#: depth levels of the overlay over the camera image (class ids 1-255 of a uint8 image)
OVERLAY_LEVELS = 255
#: colours of the loss series (others: grey)
LOST_RGB = {"dropped": (255, 150, 40), "camera_lost": (255, 60, 60)}
OTHER_RGB = (160, 160, 160)
#: extras of RunStats that count losses (the others are times, totals or fractions)
LOSS_WORDS = ("drop", "lost", "missing", "fail", "underrun", "bad")
#: plot colours: series that share a plot must be told apart without a legend
TIME_RGB = {"latency": (255, 190, 60), "processing": (90, 170, 255)}
PR_SET_PDEATHSIG = 1
#: colour codes in the Rerun binary's log lines, and its lines of routine news
_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_ROUTINE = re.compile(r"^\S+Z\s+(TRACE|DEBUG|INFO)\b")
#: how often the SDK's buffer is flushed into an .rrd file, seconds
CHECK_INTERVAL_S = 1.0

# Google's polynomial approximation of the turbo colormap (the viewer's depth colormap),
# so 3D points and flows are coloured like the depth image.
_TURBO = np.array(
    [
        [0.13572138, 4.61539260, -42.66032258, 132.13108234, -152.94239396, 59.28637943],
        [0.09140261, 2.19418839, 4.84296658, -14.18503333, 4.27729857, 2.82956604],
        [0.10667330, 12.64194608, -60.58204836, 110.36276771, -89.90310912, 27.34824973],
    ]
)


def _turbo_table() -> np.ndarray:
    """uint8 ``(256, 1, 3)`` for ``cv2.applyColorMap``: black, then the polynomial at 255
    evenly spaced levels (RGB order: the table's channels are copied as they are)."""
    t = np.linspace(0.0, 1.0, 255)
    rgb = np.clip(np.stack([t**k for k in range(6)], axis=-1) @ _TURBO.T, 0.0, 1.0)
    table = np.vstack([np.zeros((1, 3), np.uint8), (rgb * 255 + 0.5).astype(np.uint8)])
    return np.ascontiguousarray(table.reshape(256, 1, 3))


_TURBO_TABLE = _turbo_table()


def turbo_rgb(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """uint8 RGB ``(..., 3)`` of ``values`` on the turbo colormap over ``[lo, hi]`` (clipped).

    255 levels; NaN and infinities map to black.  One float pass to a level index,
    then OpenCV's colour-table lookup (a third of the time of a NumPy gather): a
    frame's maps are coloured in about a millisecond.
    """
    v = np.asarray(values, dtype=np.float32)
    if v.size == 0:
        return np.zeros(v.shape + (3,), np.uint8)
    t = (v - np.float32(lo)) * np.float32(254.0 / (hi - lo)) + np.float32(1.5)
    np.clip(t, 1.0, 255.0, out=t)  # +inf -> 255, NaN stays NaN
    t[~np.isfinite(v)] = 0.0  # the black entry
    index = t.astype(np.uint8).reshape(v.shape[0] if v.ndim else 1, -1)
    return cv2.applyColorMap(index, _TURBO_TABLE).reshape(v.shape + (3,))


def depth_levels(depth_mm_max: int, near: float, far: float, levels: int) -> np.ndarray:
    """uint8 table from depth in millimetres to the overlay's class id.

    Class 0 is "no depth" (0 mm), classes 1 to ``levels`` split ``[near, far]``
    (metres) evenly; depths outside take the first or last class.
    """
    z = np.arange(depth_mm_max + 1) / 1000.0
    level = np.floor((z - near) * ((levels - 1) / (far - near)) + 1.5)
    table = np.clip(level, 1, levels).astype(np.uint8)
    table[0] = 0
    return table


def lookup_u16(table: np.ndarray, index: np.ndarray) -> np.ndarray:
    """``table[index]`` for a 2D uint16 ``index`` (``np.take``'s result), in bands of rows.

    ``np.take`` first widens every index to int64 (15 MB for a 1600x1200 image) and
    took 5-6 ms per frame; this reads the uint16 values as they are.

    Parameters
    ----------
    table : numpy.ndarray
        ``(65536,)`` values.
    index : numpy.ndarray
        ``(h, w)`` uint16.

    Returns
    -------
    numpy.ndarray
        ``(h, w)`` of ``table``'s dtype.
    """
    out = np.empty(index.shape, table.dtype)
    run_rows(_lookup_rows, index.shape[0], table, index, out)
    return out


@nb.njit(cache=True, nogil=True, no_cfunc_wrapper=True)
def _lookup_rows(table, index, out, r0, r1):
    for i in range(r0, r1):
        for j in range(index.shape[1]):
            out[i, j] = table[index[i, j]]


def raw_image(kind, array: np.ndarray, color_model: str | None = None, **fields):
    """A Rerun image archetype over ``array``'s bytes, without copying them.

    rerun-sdk's constructors copy a NumPy image three times on the way to Arrow
    (about 2 ms for a 1600x1200 RGB frame); a contiguous array wrapped as an Arrow
    list is taken as it is.

    Parameters
    ----------
    kind : type
        ``rr.Image``, ``rr.DepthImage`` or ``rr.SegmentationImage``.
    array : numpy.ndarray
        ``(H, W)`` or ``(H, W, C)``, C-contiguous.
    color_model : str, optional
        ``rr.Image`` only: "L", "RGB" or "RGBA".
    **fields
        The archetype's other fields (``draw_order``, ``meter``, ...).
    """
    array = np.ascontiguousarray(array)
    flat = pa.array(array.reshape(-1).view(np.uint8))
    buffer = pa.ListArray.from_arrays(pa.array([0, len(flat)], pa.int32()), flat,
                                      type=_BUFFER_TYPE)  # fmt: skip
    height, width = array.shape[:2]
    fmt = rr.components.ImageFormat(
        width=width, height=height, color_model=color_model,
        channel_datatype=rr.encodings.ChannelDatatype.from_np_dtype(array.dtype),
    )  # fmt: skip
    return kind.from_fields(buffer=buffer, format=fmt, **fields)


def rerun_binary() -> Path:
    """The Rerun CLI binary shipped with rerun-sdk (not the venv's Python wrapper script)."""
    import rerun_cli

    return Path(rerun_cli.__file__).parent / "rerun"


def disable_viewer_analytics() -> None:
    """Opt out of the Rerun viewer's usage analytics (a per-user setting of the binary).

    The viewer and server, not the logging SDK, send the analytics events, so
    this runs before lightflow starts one of them.
    """
    subprocess.run(
        [str(rerun_binary()), "analytics", "disable"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        check=False,
        timeout=30,
    )


def _die_with_parent(parent_pid: int):
    """A ``preexec_fn``: the child gets SIGKILL when the thread that started it ends.

    Runs in the child between fork and exec.  If the parent is already gone
    (it died before ``prctl``), the child ends itself at once.
    """

    def preexec() -> None:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        if os.getppid() != parent_pid:
            os.kill(os.getpid(), signal.SIGKILL)

    return preexec


class RerunProcess:
    """A Rerun binary run as a child in its own process group (stopped as a group).

    Parameters
    ----------
    args : list of str
        Arguments of the binary.
    ready_text : str, optional
        A line on its stderr that says it is listening; :meth:`start` waits for it.
    log_path : Path, optional
        Without ``ready_text``: where its stderr goes (a viewer that outlives us
        must not write into a pipe nobody reads).
    die_with_parent : bool
        Kill the child when lightflow ends, however it ends (Linux parent-death
        signal).  For servers; a viewer window is left to the user.  The signal
        fires when the *thread* that called :meth:`start` ends, so start it from
        a thread that lives as long as the run (the main thread).
    """

    def __init__(
        self,
        args: list[str],
        ready_text: str | None = None,
        log_path: Path | None = None,
        die_with_parent: bool = False,
    ):
        self.args = [str(rerun_binary()), *args]
        self.ready_text = ready_text
        self.log_path = log_path
        self.die_with_parent = die_with_parent
        self.proc: subprocess.Popen | None = None
        self._ready = threading.Event()
        self._tail: collections.deque[str] = collections.deque(maxlen=5)
        self._reader: threading.Thread | None = None

    def start(self, timeout_s: float = READY_TIMEOUT_S) -> None:
        log = open(self.log_path, "wb") if self.log_path else subprocess.DEVNULL  # noqa: SIM115
        preexec = _die_with_parent(os.getpid()) if self.die_with_parent else None
        env = dict(os.environ)
        if env.get("RUST_LOG") == _QUIET_SDK:
            del env["RUST_LOG"]  # the server's "Listening" line is an INFO message
        try:
            self.proc = subprocess.Popen(
                self.args,
                env=env,
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.PIPE if self.ready_text else log,
                start_new_session=True,  # its own group: Ctrl-C and close() reach all of it
                preexec_fn=preexec,
                text=True,
                errors="replace",
            )
        except OSError as exc:
            raise DriverError(f"cannot start {self.args[0]}: {exc.strerror}") from None
        finally:
            if self.log_path:
                log.close()  # the child holds its own descriptor
        if self.ready_text is None:
            return
        self._reader = threading.Thread(target=self._read_stderr, name="rerun-stderr", daemon=True)
        self._reader.start()
        if not self._ready.wait(timeout_s) or self.proc.poll() is not None:
            last = self._tail[-1] if self._tail else "no output"
            self.stop()
            raise DriverError(f"Rerun server did not start ({' '.join(self.args[1:])}): {last}")

    def _read_stderr(self) -> None:
        # drains the pipe for the whole life of the child so it never blocks on a full pipe
        assert self.proc is not None and self.proc.stderr is not None
        for line in self.proc.stderr:
            self._tail.append(line.strip())
            if self.ready_text and self.ready_text in line:
                self._ready.set()
        self._ready.set()  # EOF: the child ended; start() checks poll()

    def exit_reason(self) -> str | None:
        """How the child ended, and its last warning or error line (None while it runs)."""
        if self.proc is None or self.proc.poll() is None:
            return None
        code = self.proc.returncode
        try:
            how = f"killed by {signal.Signals(-code).name}" if code < 0 else f"exit status {code}"
        except ValueError:
            how = f"exit status {code}"
        lines = list(self._tail)
        if self.log_path and self.log_path.exists():
            lines = self.log_path.read_text(errors="replace").strip().splitlines()
        # its log lines are coloured; a routine INFO line ("Listening ...") says nothing
        told = [_ANSI.sub("", line).strip() for line in lines]
        told = [line for line in told if line and not _ROUTINE.match(line)]
        return f"{how}: {told[-1]}" if told else how

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc else None

    def stop(self) -> None:
        """Terminate the whole process group; safe to call twice."""
        proc, self.proc = self.proc, None
        if proc is None:
            return
        if proc.poll() is None:
            try:
                os.killpg(proc.pid, signal.SIGTERM)
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
            except ProcessLookupError:
                pass
        if self._reader is not None:
            self._reader.join(timeout=5)
        if proc.stderr is not None:
            proc.stderr.close()


class RerunOutput:
    """A private recording stream on an .rrd file, a spawned viewer or a loopback server.

    Parameters
    ----------
    app_id : str
        Rerun application id.
    mode : str
        ``rrd``, ``spawn`` or ``serve``.
    path : Path, optional
        The .rrd file (``rrd`` only).
    port : int
        Port of the viewer or server on 127.0.0.1.
    save_path : Path, optional
        With ``spawn`` or ``serve``: also write everything to this .rrd, so that
        closing the viewer loses nothing.

    Attributes
    ----------
    rec : rerun.RecordingStream
        Log to this; call :meth:`pump` after each frame.
    process : RerunProcess or None
        The viewer/server child.

    Notes
    -----
    Files are written by :class:`~lightflow.app.sinks.rrd_file.RrdFile`, not by
    the SDK's own writer, which can hang on a failed write.  :meth:`pump` checks
    the file on every call and flushes at most every :data:`CHECK_INTERVAL_S` (so
    the SDK's buffer stays within a second of data): a full disk stops the run
    within a second as one :class:`DriverError` line, and the partial file is
    removed.  (The SDK's own stream of bytes, ``binary_stream``, cannot be written
    piecewise: each read is a complete .rrd of its own.)
    """

    def __init__(
        self, app_id: str, mode: str, path: Path | None = None, port: int = 9876,
        save_path: Path | None = None,
    ):
        # a private stream: other code (or tests) using the global recording is unaffected
        self.rec = rr.RecordingStream(app_id, recording_id=uuid.uuid4())
        self.mode = mode
        self.path = path
        self.port = port
        self.url = f"rerun+http://127.0.0.1:{port}/proxy"
        self.process: RerunProcess | None = None
        self.save_path = Path(save_path) if save_path is not None and mode != "rrd" else None
        self._failed = False
        self._gone = False  # the viewer or server child ended (reported once)
        self._next_check = 0.0
        self._file: RrdFile | None = None
        if mode == "rrd":
            self._open_file()
        elif mode == "serve":
            self._open_server()
        else:
            self._open_viewer()

    def _start_file(self, path: Path) -> RrdFile:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._file = RrdFile(path)
        except OSError as exc:
            raise DriverError(f"{path}: cannot write the Rerun file: {exc.strerror}") from None
        return self._file

    def _open_file(self) -> None:
        assert self.path is not None
        file = self._start_file(self.path)
        try:
            self.rec.save(file.sink_path)
        except RuntimeError as exc:
            self.discard()
            raise DriverError(f"{self.path}: cannot write the Rerun file: {exc}") from None

    def _open_server(self) -> None:
        disable_viewer_analytics()
        self.process = RerunProcess(
            ["--serve-grpc", "--bind", "127.0.0.1", "--port", str(self.port)],
            ready_text="Listening for gRPC connections",
            die_with_parent=True,
        )
        self.process.start()
        try:
            self._connect()
        except BaseException:
            self.process.stop()
            raise

    def _open_viewer(self) -> None:
        if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
            raise DriverError(
                "rerun: no display to open a viewer on (DISPLAY is not set); "
                "write a file with --rrd FILE, or use --serve"
            )
        disable_viewer_analytics()
        # the viewer hosts its own gRPC server: keep it on loopback as well.  It is left
        # running after the sink closes: it is the user's window onto the results.
        log = Path(tempfile.gettempdir()) / f"lightflow-rerun-viewer-{self.port}.log"
        self.process = RerunProcess(
            ["--bind", "127.0.0.1", "--port", str(self.port)], log_path=log
        )
        self.process.start()
        self._connect()

    def _connect(self) -> None:
        if self.save_path is None:
            self.rec.connect_grpc(self.url)
            return
        file = self._start_file(self.save_path)
        try:
            self.rec.set_sinks(rr.GrpcSink(self.url), rr.FileSink(file.sink_path))
        except RuntimeError as exc:
            self.discard()
            raise DriverError(f"{self.save_path}: cannot write the Rerun file: {exc}") from None

    def pump(self, force: bool = False) -> None:
        """Check the viewer or server and the .rrd; flush at most every CHECK_INTERVAL_S.

        A viewer closed by the user raises :class:`OutputClosed` (once); a viewer or
        server that died, or a failed write, one :class:`DriverError`.
        """
        if self._failed:
            return
        if not self._gone and self.process is not None and self.process.proc is not None \
                and self.process.proc.poll() is not None:  # fmt: skip
            self._gone = True
            self._lost_process()
        if self._file is None:
            return
        if self._file.error is not None:
            self._fail()
        now = time.monotonic()
        if not force and now < self._next_check:
            return
        self._next_check = now + CHECK_INTERVAL_S
        if self.mode == "rrd":
            self.rec.flush()  # keeps the SDK's buffer to a second of data; a viewer may lag

    def _saved(self) -> str:
        return f" (the run is in {self.save_path})" if self.save_path else ""

    def _exited(self, severed: Exception | None = None) -> DriverError:
        """The error for a viewer or server child that ended (or a connection severed)."""
        reason = self.process.exit_reason() if self.process else None
        kind = "server" if self.mode == "serve" else "viewer"
        told = f"Rerun {kind} exited ({reason})" if reason else f"Rerun: {severed}"
        return DriverError(told + self._saved())

    def _lost_process(self) -> None:
        assert self.process is not None and self.process.proc is not None
        if self.mode == "spawn" and self.process.proc.returncode == 0:
            raise OutputClosed(f"the Rerun viewer was closed{self._saved()}")
        raise self._exited()

    def _fail(self) -> None:
        assert self._file is not None and self._file.error is not None
        reason = self._file.reason()
        self.discard()
        raise DriverError(
            f"{self._file.path}: cannot write the Rerun file ({reason}); "
            "the partial file was removed"
        ) from None

    def discard(self) -> None:
        """Stop writing and delete the .rrd file: after a failure nothing half-written is left."""
        if self._file is None:
            return
        self._failed = True
        try:
            self.rec.disconnect()
        except RuntimeError:
            pass  # a viewer that went away; the file goes anyway
        self._file.finish()
        self._file.path.unlink(missing_ok=True)

    def close(self) -> None:
        """Flush and disconnect (the .rrd is complete afterwards); stop a server child.

        A viewer that died, or a file that could not be written, becomes one
        :class:`DriverError` line (once: not again after :meth:`pump` reported it).
        """
        try:
            if self._failed:
                return
            if self.mode == "rrd":
                self.rec.flush()
                self.rec.disconnect()
                self._file.finish()
                if self._file.error is not None:
                    self._fail()
                return
            severed = None
            try:
                self.rec.flush()
            except RuntimeError as exc:
                # the SDK reports a viewer that died or was closed as a severed connection
                severed = exc
            try:
                self.rec.disconnect()
            except RuntimeError as exc:
                severed = severed or exc
            if self._file is not None:
                self._file.finish()  # the saved copy is complete even when the viewer is gone
                if self._file.error is not None:
                    self._fail()
            if severed is not None and not self._gone:
                raise self._exited(severed)
        finally:
            if self.mode == "serve" and self.process is not None:
                self.process.stop()


def make_blueprint(rig: Rig, flow_range_px: tuple[float, float],
                   depth_range_m: tuple[float, float]) -> rrb.Blueprint:
    """The default layout, what an operator needs first: image with depth, then 3D, then details.

    Every view's name says what it shows and in which unit; plots that share
    a unit share a view, and no legend covers a plot (series are told apart by
    the colours named in the title).
    """
    channels = [pat.channel for _, pat in rig.patterns]
    lo, hi = flow_range_px
    near, far = depth_range_m
    details = [rrb.Spatial2DView(
        origin="world/camera", contents=["$origin/depth"], name=f"depth {near:g}-{far:g} m",
    )]  # fmt: skip
    details += [
        rrb.Spatial2DView(origin=f"flow/{ch}", name=f"{ch} flow {lo:g}-{hi:g} projector px")
        for ch in channels
    ]
    r_lo, r_hi = LOG_RATIO_RANGE
    details.append(
        rrb.Spatial2DView(origin="flow/log_ratio", name=f"log flow ratio {r_lo:g} to {r_hi:g}")
    )
    details.append(rrb.Spatial2DView(
        origin="uncertainty", name=f"predicted depth error (1 sigma) 0-{STD_RANGE_MM:g} mm",
    ))  # fmt: skip
    details.append(rrb.Spatial2DView(origin="causes", name="no depth: why (hover a colour)"))

    def plot(origin: str, name: str, **kwargs) -> rrb.TimeSeriesView:
        # no legend over the plot: series sharing a plot have fixed colours named in the title
        return rrb.TimeSeriesView(
            origin=origin, name=name, plot_legend=rrb.PlotLegend(visible=False), **kwargs
        )

    stats = rrb.Grid(
        plot("stats/rate/fps", "frame rate (fps)"),
        plot("stats/time_ms", "ms: yellow latency, blue processing"),
        plot("stats/coverage", "%: blue depth on image, green coverage"),
        plot("stats/lost", "lost: orange dropped, red camera, grey other"),
        plot("stats/rate/mib_per_s", "data rate (MiB/s)"),
        rrb.BarChartView(origin="stats/no_depth",
                         name="% of pixels per cause (bar i: cause i, as in the causes view)"),
        rrb.TextLogView(origin="log", name="notes"),
        grid_columns=2,
    )
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial2DView(
                    origin="world/camera",
                    contents=["$origin/image", "$origin/depth_overlay"],
                    name=f"camera + depth, turbo {near:g} m (blue) to {far:g} m (red)",
                ),
                rrb.Spatial3DView(
                    origin="world",
                    # the depth image would be back-projected a second time under the pinhole
                    # and the image plane would hide the points behind it from this eye
                    contents=["+ $origin/**", "- /world/camera/depth", "- /world/camera/bands/**",
                              "- /world/camera/depth_overlay", "- /world/camera/image"],
                    name="3D points, metres, coloured by depth",
                    eye_controls=rrb.EyeControls3D(
                        position=(0.45, -0.35, -0.1), look_target=(0.0, 0.0, 0.7),
                        eye_up=(0.0, -1.0, 0.0),
                    ),
                ),
            ),
            rrb.Vertical(
                rrb.Spatial2DView(
                    origin="world/camera",
                    contents=["$origin/image", "$origin/bands/**"],
                    name="bands: colour accepted, grey rejected",
                ),
                rrb.Grid(*details, grid_columns=2),
                stats,
                row_shares=[3, 3, 5],
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


class RerunSink:
    """Log every result to Rerun: an .rrd file, a spawned viewer, or a loopback server.

    Parameters
    ----------
    rig : Rig
        Camera intrinsics (for the pinhole and the 3D points) and the pattern channels.
    mode : str
        ``rrd`` (write ``path``), ``spawn`` (start a viewer window) or ``serve``
        (a gRPC server on 127.0.0.1 for viewers to connect to).
    path : str or Path, optional
        The .rrd file (``rrd`` mode only).
    compress : bool
        Log the camera image as JPEG (about 10x smaller, faster to write).
    app_id : str
        Rerun application id.
    max_points : int
        At most this many 3D points per frame (evenly subsampled).
    port : int
        Port of the server (``serve``) or viewer (``spawn``) on 127.0.0.1.
    image_plane_distance : float
        Where the camera frustum's image plane is drawn in 3D, metres.
    depth_range_m : (float, float)
        Fixed colour range of depth and of the 3D points (near, far), metres.
    flow_range_px : (float, float), optional
        Fixed colour range of the flows in projector pixels; default 0 to the
        widest line pitch of the rig's uniform patterns (40 px if none).
    save_path : str or Path, optional
        With ``spawn`` or ``serve``: also keep everything in this .rrd.
    """

    def __init__(
        self,
        rig: Rig,
        mode: str,
        path: str | Path | None = None,
        compress: bool = False,
        app_id: str = "lightflow",
        max_points: int = 100_000,
        port: int = 9876,
        image_plane_distance: float = 0.2,
        jpeg_quality: int = 90,
        depth_range_m: tuple[float, float] = DEPTH_RANGE_M,
        flow_range_px: tuple[float, float] | None = None,
        save_path: str | Path | None = None,
    ):
        if mode not in MODES:
            raise ConfigError(f"rerun mode: expected one of {', '.join(MODES)}, got {mode!r}")
        if (mode == "rrd") != (path is not None):
            raise ConfigError("rerun: a path is needed for (and only for) mode 'rrd'")
        if not 0 <= depth_range_m[0] < depth_range_m[1]:
            raise ConfigError(f"rerun depth range: expected 0 <= near < far, got {depth_range_m}")
        self.rig = rig
        self.mode = mode
        self.path = Path(path) if path is not None else None
        self.compress = compress
        self.jpeg_quality = jpeg_quality
        self.max_points = max_points
        self.port = port
        self.image_plane_distance = image_plane_distance
        self.depth_range_m = (float(depth_range_m[0]), float(depth_range_m[1]))
        if flow_range_px is None:
            pitches = [pat.pitch_px for _, pat in rig.patterns if pat.kind == "uniform"]
            flow_range_px = (0.0, max(pitches) if pitches else 40.0)
        self.flow_range_px = (float(flow_range_px[0]), float(flow_range_px[1]))
        self._overlay_ids = depth_levels(65535, *self.depth_range_m, OVERLAY_LEVELS)
        self.url = f"rerun+http://127.0.0.1:{port}/proxy"
        self._rays: dict[int, np.ndarray] = {}  # per grid stride (1: every pixel)
        self._channels = [pat.channel for _, pat in rig.patterns]
        self._closed = False
        self._series_named: set[str] = set()
        self.frames_logged = 0

        self.save_path = Path(save_path) if save_path is not None and mode != "rrd" else None
        self.output = RerunOutput(app_id, mode, self.path, port, save_path=self.save_path)
        self.rec = self.output.rec
        try:
            self.rec.send_blueprint(make_blueprint(rig, self.flow_range_px, self.depth_range_m))
            self._log_static()
            self.output.pump()
        except BaseException:
            self.output.discard()
            self.close()  # do not leave a server child behind
            raise

    @property
    def _process(self) -> RerunProcess | None:
        return self.output.process

    def _log_static(self) -> None:
        cam = self.rig.camera
        rec = self.rec
        rec.log("world", rr.ViewCoordinates.RDF, static=True)
        # hovering the causes image names the cause of each pixel
        rec.log("causes", rr.AnnotationContext([
            rr.AnnotationInfo(id=code, label=f"{name}: {meaning}", color=CAUSE_COLOURS[code])
            for code, (name, meaning) in enumerate(CAUSES)
        ]), static=True)  # fmt: skip
        # the camera sits at the world origin; its pose is logged apart from the pinhole
        # so that a moving camera (or a world frame) only changes this transform
        rec.log("world/camera", rr.Transform3D(translation=[0.0, 0.0, 0.0]), static=True)
        # the depth overlay's classes: 0 = no depth (transparent), then the depth range in
        # OVERLAY_LEVELS steps of the turbo colours; hovering names the depth
        near, far = self.depth_range_m
        levels = near + (far - near) * np.arange(OVERLAY_LEVELS) / (OVERLAY_LEVELS - 1)
        rgb = turbo_rgb(levels, near, far)
        rec.log("world/camera/depth_overlay", rr.AnnotationContext(
            [rr.AnnotationInfo(id=0, label="no depth", color=(0, 0, 0, 0))]
            + [rr.AnnotationInfo(id=k + 1, label=f"{z:.3f} m", color=tuple(int(c) for c in rgb[k]))
               for k, z in enumerate(levels)]
        ), static=True)  # fmt: skip
        rec.log(
            "world/camera",
            rr.Pinhole(
                image_from_camera=cam.K,
                width=cam.width,
                height=cam.height,
                camera_xyz=rr.ViewCoordinates.RDF,
                image_plane_distance=self.image_plane_distance,
            ),
            static=True,
        )
        for name, rgb in TIME_RGB.items():
            rec.log(f"stats/time_ms/{name}", rr.SeriesLines(colors=rgb, names=f"{name} (ms)"),
                    static=True)
        for name, rgb in LOST_RGB.items():
            rec.log(f"stats/lost/{name}", rr.SeriesLines(colors=rgb, names=name), static=True)
        rec.log("stats/coverage/depth_on_image",
                rr.SeriesLines(colors=(90, 170, 255), names="depth on image (%)"), static=True)
        rec.log("stats/coverage/moving_lit_with_depth",
                rr.SeriesLines(colors=(120, 220, 120),
                               names="moving lit pixels with depth (%), as in eval"),
                static=True)

    def write(self, result: FrameResult, stats: RunStats) -> None:
        """Log one frame's image, bands, flows, depth, points and the run statistics."""
        frame = result.frame
        rec = self.rec
        rec.set_time("frame", sequence=frame.index)
        rec.set_time("camera_time", duration=frame.timestamp)

        rgb8 = image_to_rgb8(frame.image)
        if self.compress:
            # OpenCV's libjpeg-turbo: half the time of rerun-sdk's compress() (PIL)
            bgr = cv2.cvtColor(rgb8, cv2.COLOR_RGB2BGR) if rgb8.ndim == 3 else rgb8
            _, jpeg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
            rec.log("world/camera/image", rr.EncodedImage(
                contents=jpeg.tobytes(), media_type="image/jpeg", draw_order=0.0))
        else:
            rec.log("world/camera/image",
                    raw_image(rr.Image, rgb8, "RGB" if rgb8.ndim == 3 else "L", draw_order=0.0))
        flows = dict(zip(self._channels, result.flows_grid, strict=False))
        for bands in result.bands:
            accepted, rejected = _band_strips(bands, flows.get(bands.channel), result.stride)
            rec.log(f"world/camera/bands/{bands.channel}/accepted", accepted)
            rec.log(f"world/camera/bands/{bands.channel}/rejected", rejected)
        lo, hi = self.flow_range_px
        for channel, flow in zip(self._channels, result.flows_grid, strict=False):
            rec.log(f"flow/{channel}", raw_image(rr.Image, turbo_rgb(flow, lo, hi), "RGB"))
        rec.log("flow/log_ratio", raw_image(
            rr.Image, turbo_rgb(result.log_ratio_grid, *LOG_RATIO_RANGE), "RGB"))
        if result.depth_std_grid is not None:
            std_mm = result.depth_std_grid * 1e3
            rec.log("uncertainty/depth_std",
                    raw_image(rr.Image, turbo_rgb(std_mm, 0.0, STD_RANGE_MM), "RGB"))
        if result.causes_grid is not None:
            rec.log("causes", raw_image(rr.SegmentationImage, result.causes_grid))
        # Rerun treats depth 0 as "no measurement"; hovering shows metres.  Millimetres in
        # uint16 and the overlay's class ids in uint8: a sixth of the bytes of float32 depth
        # and an RGBA overlay, which Rerun copies and writes on every frame.  OpenCV's
        # conversion rounds, saturates and turns NaN into 0 in one pass
        depth_mm = cv2.multiply(np.ascontiguousarray(result.depth, np.float32), 1000.0,
                                dtype=cv2.CV_16U)  # fmt: skip
        rec.log("world/camera/depth", raw_image(
            rr.DepthImage, depth_mm, meter=1000.0, colormap=COLORMAP,
            depth_range=tuple(1000.0 * z for z in self.depth_range_m), draw_order=1.0,  # in mm
        ))  # fmt: skip
        # over the camera image: the same colours, see-through, and nothing where no depth
        rec.log("world/camera/depth_overlay", raw_image(
            rr.SegmentationImage, lookup_u16(self._overlay_ids, depth_mm),
            opacity=OVERLAY_ALPHA / 255.0, draw_order=1.0,
        ))  # fmt: skip
        # the points of the analysis grid: the depth's own samples (the full-resolution
        # map adds only interpolated ones), a sixteenth of the work
        if result.depth_grid is not None:
            points, _ = depth_to_points(result.depth_grid, self._rays_at(result.stride), None,
                                        self.max_points)  # fmt: skip
        else:
            points, _ = depth_to_points(result.depth, self._rays_at(1), None, self.max_points)
        rec.log("world/points", rr.Points3D(
            # a few screen points wide whatever the zoom: sparse depth stays visible
            points, colors=turbo_rgb(points[:, 2], *self.depth_range_m),
            radii=rr.components.Radius.ui_points(2.5),
        ))  # fmt: skip
        self._log_stats(result, stats)
        self.frames_logged += 1
        self.output.pump()

    def _rays_at(self, stride: int) -> np.ndarray:
        """Camera rays (z = 1) through the centres of the ``stride`` x ``stride`` cells."""
        if stride not in self._rays:
            self._rays[stride] = camera_rays(self.rig.camera, stride).astype(np.float32)
        return self._rays[stride]

    def _log_stats(self, result: FrameResult, stats: RunStats) -> None:
        rec = self.rec
        rec.log("stats/rate/fps", rr.Scalars(stats.fps))
        rec.log("stats/rate/mib_per_s", rr.Scalars(stats.mib_per_s))
        processing = result.timings_ms.get("total")
        if self.frames_logged == 0:
            # compilation and warm-up: tens of seconds that would flatten every later point
            text = f"frame {result.frame.index}: latency {stats.latency_ms:.0f} ms"
            if processing is not None:
                text += f", processing {processing:.0f} ms"
            rec.log("log", rr.TextLog(
                text + " (first frame: includes compilation; left out of the time plot)",
                level=rr.TextLogLevel.INFO,
            ))  # fmt: skip
        else:
            rec.log("stats/time_ms/latency", rr.Scalars(stats.latency_ms))
            if processing is not None:
                rec.log("stats/time_ms/processing", rr.Scalars(processing))
        rec.log("stats/coverage/depth_on_image", rr.Scalars(100.0 * result.coverage))
        if result.cause_counts is not None:
            counts = result.cause_counts
            rec.log("stats/no_depth", rr.BarChart(100.0 * counts / max(1, counts.sum())))
        truth = result.frame.extras.get("truth")
        if truth is not None:
            share = coverage(result.depth, truth, n_projectors=len(self.rig.projectors))
            if np.isfinite(share):
                rec.log("stats/coverage/moving_lit_with_depth", rr.Scalars(100.0 * share))
        rec.log("stats/lost/dropped", rr.Scalars(float(stats.dropped)))
        rec.log("stats/lost/camera_lost", rr.Scalars(float(stats.camera_lost)))
        # queue drops and the loss counters of live cameras (underruns, missing packets,
        # ...); other extras are times or totals, not losses, and have their own plots
        for key, value in stats.extra.items():
            if isinstance(value, (int, float)) and any(w in key for w in LOSS_WORDS):
                if key not in self._series_named:
                    self._series_named.add(key)
                    rec.log(f"stats/lost/{key}", rr.SeriesLines(colors=OTHER_RGB, names=key),
                            static=True)
                rec.log(f"stats/lost/{key}", rr.Scalars(float(value)))

    def close(self) -> None:
        """Flush everything (the .rrd is complete afterwards) and stop a server child."""
        if self._closed:
            return
        self._closed = True
        self.output.close()

    def describe(self) -> str:
        """How the user gets to see what was logged."""
        if self.mode == "rrd":
            n = self.frames_logged
            return f"Rerun: {n} frames in {self.path}; open with `rerun {self.path}`"
        saved = f"; saved in {self.save_path}" if self.save_path else ""
        if self.mode == "serve":
            return f"Rerun server on 127.0.0.1:{self.port}: `rerun --connect {self.url}`{saved}"
        return f"Rerun viewer on 127.0.0.1:{self.port} ({self.frames_logged} frames sent){saved}"


def _band_strips(
    bands: BandSet, flow_grid: np.ndarray | None, stride: int
) -> tuple[rr.LineStrips2D, rr.LineStrips2D]:
    """Accepted bands in the channel's colour, rejected ones thinner in grey.

    One horizontal segment per band, from its start to its end column.  A band
    is accepted when it passed the band checks *and* its grid cell kept a flow:
    the bands of a static wall pass the first test but give no flow, and are
    drawn as rejected.
    """
    rows = np.asarray(bands.rows, dtype=np.float32)
    starts = np.asarray(bands.starts, np.float32)
    ends = np.asarray(bands.ends, np.float32)
    segments = np.stack(
        [np.stack([starts, rows], axis=-1), np.stack([ends, rows], axis=-1)], axis=1
    )
    accepted = np.asarray(bands.valid, dtype=bool).copy()
    if flow_grid is not None and len(rows):
        gh, gw = flow_grid.shape
        gy = np.clip((rows // stride).astype(np.intp), 0, gh - 1)
        gx = np.clip((0.5 * (starts + ends) // stride).astype(np.intp), 0, gw - 1)
        accepted &= np.isfinite(flow_grid[gy, gx])
    rgb = CHANNEL_RGB.get(bands.channel, (255, 255, 255))
    return (
        rr.LineStrips2D(_segments_arrow(segments[accepted]), colors=rgb, radii=0.6,
                        draw_order=3.0),
        rr.LineStrips2D(_segments_arrow(segments[~accepted]), colors=REJECTED_RGB, radii=0.4,
                        draw_order=2.0),
    )


#: Arrow type of a batch of 2D line strips (what rerun-sdk builds from native data)
_STRIPS_TYPE = rr.components.LineStrip2DBatch([]).as_arrow_array().type
#: Arrow type of an image's buffer (a list of bytes)
_BUFFER_TYPE = rr.components.ImageBufferBatch([]).as_arrow_array().type


def _segments_arrow(segments: np.ndarray) -> pa.Array:
    """``(N, 2, 2)`` two-point strips as one Arrow list array, built with NumPy.

    rerun-sdk accepts such an array as it is; from NumPy it walks the strips
    one by one in Python (about 20 000 a frame here, 10-25 ms).
    """
    flat = pa.array(np.ascontiguousarray(segments, np.float32).reshape(-1))
    points = pa.FixedSizeListArray.from_arrays(flat, type=_STRIPS_TYPE.value_type)
    offsets = pa.array(np.arange(0, 2 * len(segments) + 1, 2, dtype=np.int32))
    return pa.ListArray.from_arrays(offsets, points, type=_STRIPS_TYPE)
