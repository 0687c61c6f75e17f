"""Live capture loop with a free-running simulated camera and a fake pattern output."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from rerun.chunk import RrdReader

from lightflow.app.core.rig import load_rig
from lightflow.app.sinks.calibration_sink import CalibrationSink
from lightflow.calibration.gamma import measure_ramps
from lightflow.calibration.live import calibrate_live
from lightflow.calibration.session import ProjectorSpec, read_session
from lightflow.calibration.simulate import (
    DEFAULT_BOARD,
    SimParams,
    _PlaneView,
    checkerboard_albedo,
    generate_poses,
    scaled_rig,
)
from lightflow.drivers.base import Camera, Frame


class _Scene:
    """The board pose the user holds and what each projector shows."""

    def __init__(self, rig, poses):
        self.rig, self.poses, self.pose = rig, poses, -1
        self.params = SimParams(supersample=1)
        self.views = {}
        self.shown = {p.name: np.zeros((p.height, p.width), np.float32) for p in rig.projectors}
        self.lock = threading.Lock()

    def next_pose(self, prompt):
        if "grey ramp" in prompt:
            return  # the user keeps the (light) board in place
        with self.lock:
            self.pose += 1
            R, t = self.poses[self.pose]
            alb = checkerboard_albedo(DEFAULT_BOARD, self.params)
            self.views = {p.name: _PlaneView(self.rig.camera, p, R, t, alb, self.params)
                          for p in self.rig.projectors}

    def render(self, rng):
        with self.lock:
            imgs = [v.render(self.shown[n], rng).astype(np.float32) for n, v in self.views.items()]
        return np.clip(sum(imgs), 0, 255).astype(np.uint8)


class _Outputs:
    def __init__(self, scene):
        self.scene = scene

    def show(self, projector, image):
        with self.scene.lock:
            self.scene.shown[projector] = image[..., 0].astype(np.float32)

    def wait_presented(self, timeout=None):
        return True


class _Camera(Camera):
    uri = "sim:"

    def __init__(self, scene):
        self.scene, self._stop = scene, threading.Event()

    def open(self):
        pass

    def close(self):
        pass

    @property
    def size(self):
        return (self.scene.rig.camera.width, self.scene.rig.camera.height)

    @property
    def exposure_s(self):
        return 0.01

    def set_exposure(self, seconds):
        return 0.01

    def stop(self):
        self._stop.set()

    def frames(self):
        rng = np.random.default_rng(0)
        i = 0
        while not self._stop.is_set():
            yield Frame(i, 0.0, 0.01, np.repeat(self.scene.render(rng)[..., None], 3, -1))
            i += 1


def _chunks_by_entity(path):
    out = {}
    for chunk in RrdReader(path).stream():
        out.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
    return out


def _column(batches, name):
    return [v for rb in batches if name in rb.schema.names for v in rb.column(name).to_pylist()]


def test_live_capture_writes_a_valid_session(tmp_path):
    rig = scaled_rig(load_rig("app/rigs/two-projector.json"), 0.25, 0.1)  # 400x300, 128x80
    poses = generate_poses(rig, DEFAULT_BOARD, 3, seed=5)
    poses.insert(1, poses[0])  # the user holds the same pose twice: rejected
    scene = _Scene(rig, poses)
    said = []
    specs = [ProjectorSpec(p.name, p.width, p.height, p.patterns) for p in rig.projectors]
    rrd = tmp_path / "progress.rrd"
    sink = CalibrationSink(DEFAULT_BOARD, [p.name for p in specs], "rrd", path=rrd)
    session = calibrate_live(_Camera(scene), _Outputs(scene), DEFAULT_BOARD, specs, tmp_path,
                             n_poses=3, ask=scene.next_pose, say=said.append,
                             ramp_levels=(0, 255, 64, 128, 192), on_pose=sink.log)
    sink.close()
    assert [p.name for p in session.poses] == ["pose00", "pose01", "pose02"]
    assert any("too similar to pose00" in s for s in said)
    s = read_session(tmp_path)
    assert len(s.poses) == 3 and len(s.poses[2].frames["right"]) == 2 + 2 * (7 + 7)
    frames = list(s.iter_frames(s.poses[0], s.projectors[0]))
    assert frames[0].mean() > frames[1].mean() + 5  # white brighter than black

    # the grey ramp after the poses: CAL/gamma/ with the simulated projectors' gamma 2.2
    assert (tmp_path / "gamma" / "ramp.json").is_file()
    assert sorted(p.name for p in (tmp_path / "gamma" / "left").iterdir()) == [
        f"{i:03d}.png" for i in range(5)]
    gammas = measure_ramps(tmp_path)
    assert set(gammas) == {"left", "right"}
    for r in gammas.values():
        assert r.gamma == pytest.approx(2.2, abs=0.1)

    # Rerun progress: 4 attempts (one rejected), corners, decoded maps, poses in 3D
    assert sink.describe() == f"Rerun: 4 attempts, 3 poses captured in {rrd}; open with " \
        f"`rerun {rrd}`"
    ent = _chunks_by_entity(rrd)
    for name in ["/camera/image", "/camera/image/corners", "/projectors/left/column",
                 "/projectors/left/row", "/projectors/right/column", "/projectors/right/row",
                 "/world/camera", "/world/boards/pose00", "/world/boards/pose02/board",
                 "/world/boards/pose01/normal", "/poses/captured", "/status"]:
        assert name in ent, name
    assert sorted(_column(ent["/camera/image"], "attempt")) == [0, 1, 2, 3]
    corners = _column(ent["/camera/image/corners"], "Points2D:positions")
    assert [len(c) for c in corners] == [54] * 4
    assert sorted(_column(ent["/projectors/left/column"], "attempt")) == [0, 2, 3]
    fmt = _column(ent["/projectors/left/column"], "DepthImage:format")[0][0]
    buf = bytes(_column(ent["/projectors/left/column"], "DepthImage:buffer")[0][0])
    cols = np.frombuffer(buf, np.float32).reshape(fmt["height"], fmt["width"])
    assert cols.shape == (300, 400) and cols.max() <= 128 and (cols > 0).mean() > 0.2
    assert [v[0] for v in _column(ent["/poses/captured"], "Scalars:scalars")] == [1.0, 2.0, 3.0]
    texts = [t[0] for t in _column(ent["/status"], "TextLog:text")]
    assert "pose01: too similar to pose00" in texts[1] and "3/3 poses" in texts[3]


def test_a_closed_viewer_ends_the_logging_not_the_session(tmp_path):
    from lightflow.app.core.errors import OutputClosed
    from lightflow.calibration.live import PoseView

    sink = CalibrationSink(DEFAULT_BOARD, ["left", "right"], "rrd", path=tmp_path / "p.rrd")
    pumped = []

    def pump(force=False):
        pumped.append(force)
        if len(pumped) == 3:  # the user closes the viewer during the third attempt
            raise OutputClosed("the Rerun viewer was closed")

    sink.output.pump = pump
    image = np.zeros((80, 100), np.float32)
    for k in range(4):
        sink.log(PoseView("pose00", k, image, None, False, "no board found", None, None, {}, 0))
    sink.close()
    assert sink.closed_at == 3 and sink.attempts == 3 and len(pumped) == 3
