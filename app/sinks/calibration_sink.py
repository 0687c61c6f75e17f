"""Rerun view of a live calibration: what the camera sees, what was decoded, the poses so far.

Entity layout (on the ``attempt`` timeline, one step per pose attempt)::

    camera/image                       grey camera image under all-white light
    camera/image/corners               Points2D: board corners (green: captured,
                                       orange: rejected; empty: board not found)
    projectors/<name>/column|row       decoded projector column / row of each camera
                                       pixel (DepthImage for its colormap: value is
                                       column + 1, 0 = not decoded); captured poses
    world/camera                       Pinhole (static) with guessed intrinsics
    world/boards/<pose>                Transform3D (rough board pose) with a Boxes3D
                                       outline of the board and an Arrows3D normal;
                                       they stay, so the 3D view shows every pose so far
    poses/captured, poses/tilt_deg     Scalars: poses captured (count), tilt of the last
                                       captured board (degrees), each in its own plot
    status                             TextLog: what happened, in plain words

The recording stream is a :class:`~lightflow.app.sinks.rerun_sink.RerunOutput`, as
for the depth sink (an .rrd file written by this process, or a viewer spawned on
127.0.0.1).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from lightflow.app.core.errors import ConfigError, OutputClosed
from lightflow.app.sinks.rerun_sink import RerunOutput, RerunProcess
from lightflow.calibration.live import PoseView, guessed_K
from lightflow.calibration.session import Board

MODES = ("rrd", "spawn")
ACCEPTED_RGB = (64, 220, 64)
REJECTED_RGB = (255, 150, 40)


def make_blueprint(projectors: list[str]) -> rrb.Blueprint:
    """Camera with corners, the decoded maps of each projector, 3D poses, pose plots, status."""
    maps = [rrb.Spatial2DView(origin=f"projectors/{name}/{axis}", name=f"{name} {axis}")
            for name in projectors for axis in ("column", "row")]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial2DView(origin="camera/image", name="camera + corners"),
                rrb.Grid(*maps),
            ),
            rrb.Vertical(
                rrb.Spatial3DView(origin="world", name="board poses (rough)"),
                # a count and an angle: one plot each, no legend over the lines
                rrb.Horizontal(
                    rrb.TimeSeriesView(origin="poses/captured", name="poses captured",
                                       plot_legend=rrb.PlotLegend(visible=False)),
                    rrb.TimeSeriesView(origin="poses/tilt_deg", name="board tilt (deg)",
                                       plot_legend=rrb.PlotLegend(visible=False)),
                ),
                rrb.TextLogView(origin="status", name="status"),
                row_shares=[3, 1, 1],
            ),
        ),
        collapse_panels=True,
    )


class CalibrationSink:
    """Logs every :class:`~lightflow.calibration.live.PoseView` to Rerun.

    Parameters
    ----------
    board : Board
        The checkerboard (its outline in the 3D view).
    projectors : list of str
        Projector names (the blueprint's map views).
    mode : str
        ``rrd`` (write ``path``) or ``spawn`` (start a viewer window).
    path : str or Path, optional
        The .rrd file (``rrd`` mode only).
    port : int
        Port of the spawned viewer on 127.0.0.1.
    """

    def __init__(self, board: Board, projectors: list[str], mode: str,
                 path: str | Path | None = None, port: int = 9876,
                 app_id: str = "lightflow-calibration"):
        if mode not in MODES:
            raise ConfigError(f"rerun mode: expected one of {', '.join(MODES)}, got {mode!r}")
        if (mode == "rrd") != (path is not None):
            raise ConfigError("rerun: a path is needed for (and only for) mode 'rrd'")
        self.board = board
        self.mode = mode
        self.path = Path(path) if path is not None else None
        self.port = port
        self.attempts = 0
        self.captured = 0
        self._static_done = False
        self._closed = False
        #: the attempt after which the user closed the viewer (None: open)
        self.closed_at: int | None = None
        self.output = RerunOutput(app_id, mode, self.path, port)
        self.rec = self.output.rec
        self._process: RerunProcess | None = self.output.process
        self.rec.send_blueprint(make_blueprint(list(projectors)))
        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)
        self.output.pump()

    def _log_camera(self, size: tuple[int, int]) -> None:
        w, h = size
        self.rec.log("world/camera", rr.Pinhole(image_from_camera=guessed_K(size), width=w,
                                                height=h, camera_xyz=rr.ViewCoordinates.RDF,
                                                image_plane_distance=0.1), static=True)
        self._static_done = True

    def log(self, view: PoseView) -> None:
        """Log one attempt (called from the capture thread).

        A viewer the user closed ends the logging, not the session: its poses are
        still captured and saved (:meth:`describe` says when it was closed).
        """
        if self.closed_at is not None:
            return
        rec = self.rec
        img = view.image
        if not self._static_done:
            self._log_camera((img.shape[1], img.shape[0]))
        rec.set_time("attempt", sequence=view.attempt)
        rec.log("camera/image", rr.Image(np.clip(np.rint(img), 0, 255).astype(np.uint8)))
        if view.corners is None:
            rec.log("camera/image/corners", rr.Points2D(np.zeros((0, 2), np.float32)))
        else:
            rgb = ACCEPTED_RGB if view.accepted else REJECTED_RGB
            rec.log("camera/image/corners", rr.Points2D(view.corners.astype(np.float32),
                                                        colors=rgb, radii=2.0))
        rec.log("status", rr.TextLog(view.message,
                                     level=rr.TextLogLevel.INFO if view.accepted
                                     else rr.TextLogLevel.WARN))
        if view.accepted:
            for name, dec in view.decoded.items():
                for k, axis in enumerate(("column", "row")):
                    value = np.where(dec.valid, dec.proj[..., k] + 1, 0).astype(np.float32)
                    rec.log(f"projectors/{name}/{axis}",
                            rr.DepthImage(value, meter=1.0, colormap="turbo"))
            if view.R is not None:
                self._log_board(view)
            self.captured = view.captured
            rec.log("poses/captured", rr.Scalars(float(view.captured)))
        self.attempts += 1
        try:
            self.output.pump()
        except OutputClosed:
            self.closed_at = self.attempts

    def _log_board(self, view: PoseView) -> None:
        b = self.board
        size = np.array([(b.columns + 1) * b.square_m, (b.rows + 1) * b.square_m])
        centre = np.array([(b.columns - 1) / 2 * b.square_m, (b.rows - 1) / 2 * b.square_m, 0])
        path = f"world/boards/{view.name}"
        self.rec.log(path, rr.Transform3D(translation=view.t, mat3x3=view.R))
        self.rec.log(f"{path}/board", rr.Boxes3D(centers=[centre],
                                                 half_sizes=[[*(size / 2), 0.001]],
                                                 colors=ACCEPTED_RGB, labels=view.name))
        normal = view.R[:, 2] if view.R[2, 2] < 0 else -view.R[:, 2]  # towards the camera
        self.rec.log(f"{path}/normal", rr.Arrows3D(origins=[centre],
                                                   vectors=[view.R.T @ normal * 0.1]))
        tilt = math.degrees(math.acos(min(1.0, abs(float(view.R[2, 2])))))
        self.rec.log("poses/tilt_deg", rr.Scalars(tilt))

    def close(self) -> None:
        """Flush everything (the .rrd is complete afterwards)."""
        if self._closed:
            return
        self._closed = True
        self.output.close()

    def describe(self) -> str:
        """How the user gets to see what was logged."""
        n = f"{self.attempts} attempts, {self.captured} poses captured"
        if self.mode == "rrd":
            return f"Rerun: {n} in {self.path}; open with `rerun {self.path}`"
        if self.closed_at is not None:
            return f"Rerun viewer on 127.0.0.1:{self.port} ({n}; closed after {self.closed_at})"
        return f"Rerun viewer on 127.0.0.1:{self.port} ({n})"
