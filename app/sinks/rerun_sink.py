"""Rerun sink: camera image, bands, flows, depth, 3D points and live stats.

Entity layout (all per frame on the ``frame`` timeline, plus ``camera_time``)::

    camera                      Pinhole (static): 2D entities below know the intrinsics
    camera/image                RGB image (JPEG when compress=True)
    camera/image/bands/<ch>     LineStrips2D, one segment per detected band
    camera/depth                DepthImage, metres (0 = no estimate)
    flow/<ch>, flow/log_ratio   Tensor on the analysis grid (colormapped in TensorViews)
    world/camera                Pinhole (static) at the origin of the 3D view
    world/camera/points         Points3D, camera frame, metres, subsampled
    stats/fps|latency_ms|dropped|coverage|mib_per_s|<camera counters>   Scalars

Network: ``serve`` and ``spawn`` run the Rerun binary as a child process bound to
127.0.0.1 only; the SDK's own ``serve_grpc`` has no bind option and listens on
every interface, which would publish camera images to the network.
"""

from __future__ import annotations

import collections
import os
import signal
import subprocess
import tempfile
import threading
import uuid
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from lightflow.app.errors import ConfigError, DriverError
from lightflow.app.geometry import camera_rays
from lightflow.app.results import FrameResult, RunStats
from lightflow.app.rig import Rig
from lightflow.app.sinks.ply import depth_to_points, image_to_rgb8

MODES = ("rrd", "spawn", "serve")
#: display colour of each pattern channel; invalid bands are drawn dimmed
CHANNEL_RGB = {"red": (255, 64, 64), "green": (64, 255, 64), "blue": (80, 140, 255)}
DIM = 0.3
READY_TIMEOUT_S = 30.0


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
    """

    def __init__(
        self, args: list[str], ready_text: str | None = None, log_path: Path | None = None
    ):
        self.args = [str(rerun_binary()), *args]
        self.ready_text = ready_text
        self.log_path = log_path
        self.proc: subprocess.Popen | None = None
        self._ready = threading.Event()
        self._tail: collections.deque[str] = collections.deque(maxlen=5)
        self._reader: threading.Thread | None = None

    def start(self, timeout_s: float = READY_TIMEOUT_S) -> None:
        log = open(self.log_path, "wb") if self.log_path else subprocess.DEVNULL  # noqa: SIM115
        try:
            self.proc = subprocess.Popen(
                self.args,
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.PIPE if self.ready_text else log,
                start_new_session=True,  # its own group: Ctrl-C and close() reach all of it
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
        """The last line the child printed, if it has exited (None while it runs)."""
        if self.proc is None or self.proc.poll() is None:
            return None
        lines = list(self._tail)
        if self.log_path and self.log_path.exists():
            lines = self.log_path.read_text(errors="replace").strip().splitlines()
        return lines[-1].strip() if lines else f"exit status {self.proc.returncode}"

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


def make_blueprint(rig: Rig) -> rrb.Blueprint:
    """The default layout: camera + bands, depth, 3D points, flows, stats."""
    channels = [pat.channel for _, pat in rig.patterns]
    colormap = rrb.TensorScalarMapping(colormap="turbo")
    flows = [
        rrb.TensorView(origin=f"flow/{ch}", name=f"flow {ch}", scalar_mapping=colormap)
        for ch in channels
    ]
    flows.append(rrb.TensorView(origin="flow/log_ratio", name="log ratio", scalar_mapping=colormap))
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial2DView(
                    origin="camera",
                    contents=["camera/image", "camera/image/bands/**"],
                    name="camera + bands",
                ),
                rrb.Spatial2DView(origin="camera", contents=["camera/depth"], name="depth"),
            ),
            rrb.Vertical(
                rrb.Spatial3DView(origin="world", name="points (camera frame)"),
                rrb.Horizontal(*flows),
                rrb.TimeSeriesView(origin="stats", name="stats"),
                row_shares=[3, 2, 2],
            ),
        ),
        collapse_panels=True,
    )


def open_stream(
    app_id: str, mode: str, path: Path | None = None, port: int = 9876
) -> tuple[rr.RecordingStream, RerunProcess | None]:
    """A private recording stream on a file, a spawned viewer or a loopback server.

    Returns the stream and the viewer/server child process (None for a file).
    The viewer and the server listen on 127.0.0.1 only; viewer analytics are off.
    """
    # a private stream: other code (or tests) using the global recording is unaffected
    rec = rr.RecordingStream(app_id, recording_id=uuid.uuid4())
    url = f"rerun+http://127.0.0.1:{port}/proxy"
    if mode == "rrd":
        path.parent.mkdir(parents=True, exist_ok=True)
        rec.save(path)
        return rec, None
    if mode == "serve":
        disable_viewer_analytics()
        process = RerunProcess(
            ["--serve-grpc", "--bind", "127.0.0.1", "--port", str(port)],
            ready_text="Listening for gRPC connections",
        )
        process.start()
        try:
            rec.connect_grpc(url)
        except BaseException:
            process.stop()
            raise
        return rec, process
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise DriverError(
            "rerun: no display to open a viewer on (DISPLAY is not set); "
            "write a file with --rrd FILE, or use --serve"
        )
    disable_viewer_analytics()
    # the viewer hosts its own gRPC server: keep it on loopback as well.  It is left
    # running after the sink closes: it is the user's window onto the results.
    log = Path(tempfile.gettempdir()) / f"lightflow-rerun-viewer-{port}.log"
    process = RerunProcess(["--bind", "127.0.0.1", "--port", str(port)], log_path=log)
    process.start()
    rec.connect_grpc(url)
    return rec, process


def flush_stream(rec: rr.RecordingStream, process: RerunProcess | None) -> None:
    """Flush and disconnect; a viewer that died becomes one DriverError line."""
    try:
        rec.flush()
        rec.disconnect()
    except RuntimeError as exc:
        # the SDK reports a viewer that died or was closed as a severed connection
        reason = process.exit_reason() if process else None
        raise DriverError(f"Rerun viewer exited: {reason}" if reason else f"Rerun: {exc}") from None


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
    ):
        if mode not in MODES:
            raise ConfigError(f"rerun mode: expected one of {', '.join(MODES)}, got {mode!r}")
        if (mode == "rrd") != (path is not None):
            raise ConfigError("rerun: a path is needed for (and only for) mode 'rrd'")
        self.rig = rig
        self.mode = mode
        self.path = Path(path) if path is not None else None
        self.compress = compress
        self.jpeg_quality = jpeg_quality
        self.max_points = max_points
        self.port = port
        self.image_plane_distance = image_plane_distance
        self.url = f"rerun+http://127.0.0.1:{port}/proxy"
        self._process: RerunProcess | None = None
        self._rays = camera_rays(rig.camera).astype(np.float32)
        self._channels = [pat.channel for _, pat in rig.patterns]
        self._closed = False
        self.frames_logged = 0

        self.rec, self._process = open_stream(app_id, mode, self.path, port)
        try:
            self.rec.send_blueprint(make_blueprint(rig))
            self._log_static()
        except BaseException:
            self.close()  # do not leave a server child behind
            raise

    def _log_static(self) -> None:
        cam = self.rig.camera
        pinhole = rr.Pinhole(
            image_from_camera=cam.K,
            width=cam.width,
            height=cam.height,
            camera_xyz=rr.ViewCoordinates.RDF,
        )
        self.rec.log("camera", pinhole, static=True)
        self.rec.log(
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
        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)

    def write(self, result: FrameResult, stats: RunStats) -> None:
        """Log one frame's image, bands, flows, depth, points and the run statistics."""
        frame = result.frame
        rec = self.rec
        rec.set_time("frame", sequence=frame.index)
        rec.set_time("camera_time", duration=frame.timestamp)

        rgb8 = image_to_rgb8(frame.image)
        image = rr.Image(rgb8, color_model="RGB")
        rec.log("camera/image", image.compress(self.jpeg_quality) if self.compress else image)
        for bands in result.bands:
            rec.log(f"camera/image/bands/{bands.channel}", _band_strips(bands))
        for channel, flow in zip(self._channels, result.flows_grid, strict=False):
            rec.log(f"flow/{channel}", rr.Tensor(flow.astype(np.float32), dim_names=("y", "x")))
        rec.log(
            "flow/log_ratio",
            rr.Tensor(result.log_ratio_grid.astype(np.float32), dim_names=("y", "x")),
        )
        # Rerun treats depth 0 as "no measurement"; NaN is not documented as such
        depth = np.nan_to_num(result.depth.astype(np.float32), nan=0.0)
        rec.log("camera/depth", rr.DepthImage(depth, meter=1.0, colormap="turbo"))
        points, colors = depth_to_points(result.depth, self._rays, frame.image, self.max_points)
        rec.log("world/camera/points", rr.Points3D(points, colors=colors, radii=0.0015))
        rec.log("stats/fps", rr.Scalars(stats.fps))
        rec.log("stats/latency_ms", rr.Scalars(stats.latency_ms))
        rec.log("stats/dropped", rr.Scalars(float(stats.dropped)))
        rec.log("stats/coverage", rr.Scalars(result.coverage))
        rec.log("stats/mib_per_s", rr.Scalars(stats.mib_per_s))
        rec.log("stats/camera_lost", rr.Scalars(float(stats.camera_lost)))
        # transport counters of live cameras: underruns, failures, missing packets, ...
        for key, value in stats.extra.items():
            if isinstance(value, (int, float)):
                rec.log(f"stats/{key}", rr.Scalars(float(value)))
        self.frames_logged += 1

    def close(self) -> None:
        """Flush everything (the .rrd is complete afterwards) and stop a server child."""
        if self._closed:
            return
        self._closed = True
        try:
            flush_stream(self.rec, self._process)
        finally:
            if self.mode == "serve" and self._process is not None:
                self._process.stop()

    def describe(self) -> str:
        """How the user gets to see what was logged."""
        if self.mode == "rrd":
            n = self.frames_logged
            return f"Rerun: {n} frames in {self.path}; open with `rerun {self.path}`"
        if self.mode == "serve":
            return f"Rerun server on 127.0.0.1:{self.port}: `rerun --connect {self.url}`"
        return f"Rerun viewer on 127.0.0.1:{self.port} ({self.frames_logged} frames sent)"


def _band_strips(bands) -> rr.LineStrips2D:
    """One horizontal segment per band, in the channel's colour, dimmed when invalid."""
    rows = np.asarray(bands.rows, dtype=np.float32)
    segments = np.stack(
        [
            np.stack([np.asarray(bands.starts, np.float32), rows], axis=-1),
            np.stack([np.asarray(bands.ends, np.float32), rows], axis=-1),
        ],
        axis=1,
    )
    base = np.array(CHANNEL_RGB.get(bands.channel, (255, 255, 255)), dtype=np.float32)
    valid = np.asarray(bands.valid, dtype=bool)
    colors = np.where(valid[:, None], base, base * DIM).astype(np.uint8)
    return rr.LineStrips2D(segments, colors=colors, radii=0.5)
