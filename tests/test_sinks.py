"""File sinks: depth .npy export, PLY export, recorder sink."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lightflow.app.errors import OutputError
from lightflow.app.geometry import camera_rays
from lightflow.app.recording import load_frame, read_recording
from lightflow.app.results import FrameResult, RunStats
from lightflow.app.rig import load_rig
from lightflow.app.sinks.depth_export import DepthExportSink
from lightflow.app.sinks.ply import PlyExportSink
from lightflow.app.sinks.recorder import RecorderSink
from lightflow.drivers.base import Frame

RIG_FILE = Path(__file__).resolve().parents[1] / "app" / "rigs" / "two-projector.json"


@pytest.fixture(scope="module")
def rig():
    return load_rig(RIG_FILE).scaled(0.05)  # 80x60


def make_result(rig, index=7, dtype=np.uint8) -> FrameResult:
    h, w = rig.camera.height, rig.camera.width
    yy, xx = np.mgrid[0:h, 0:w]
    depth = (0.5 + 0.01 * xx).astype(np.float32)
    depth[:, : w // 2] = np.nan  # left half: no estimate
    image = np.stack([xx * 3, yy * 4, np.full_like(xx, 200)], axis=-1).astype(dtype)
    frame = Frame(index, index / 30, 0.02, image)
    grid = np.zeros((h // 4, w // 4), np.float32)
    return FrameResult(frame, depth, [grid, grid], grid, [], 4, coverage=0.5)


def test_depth_export(tmp_path, rig):
    sink = DepthExportSink(tmp_path / "out")
    result = make_result(rig)
    sink.write(result, RunStats())
    sink.close()
    arr = np.load(tmp_path / "out" / "000007.npy")
    assert arr.dtype == np.float32 and arr.shape == (60, 80)
    assert np.isnan(arr[:, :40]).all()
    np.testing.assert_array_equal(arr[:, 40:], result.depth[:, 40:])
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["000007.npy"]  # no tmp left


def read_ply(path: Path) -> np.ndarray:
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    assert header[:2] == ["ply", "format binary_little_endian 1.0"]
    n = int(next(line.split()[2] for line in header if line.startswith("element vertex")))
    props = [line.split()[1:] for line in header if line.startswith("property")]
    assert props == [["float", "x"], ["float", "y"], ["float", "z"],
                     ["uchar", "red"], ["uchar", "green"], ["uchar", "blue"]]  # fmt: skip
    dtype = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                      ("red", "u1"), ("green", "u1"), ("blue", "u1")])  # fmt: skip
    assert len(data) - end == n * dtype.itemsize
    return np.frombuffer(data, dtype=dtype, offset=end)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_ply_export_image_colours_world_axes(tmp_path, rig, dtype):
    sink = PlyExportSink(tmp_path / "ply", rig, colors="image")
    result = make_result(rig, dtype=dtype)
    if dtype == np.uint16:
        result.frame.image[...] <<= 4  # 12-bit data: the stretch makes it as bright as 8-bit
    top = 16 if dtype == np.uint16 else 1
    sink.write(result, RunStats())
    sink.close()
    v = read_ply(tmp_path / "ply" / "000007.ply")
    assert len(v) == 60 * 40  # every pixel with a depth
    rays = camera_rays(rig.camera)
    # first point: row 0, column 40 (row-major order of the valid pixels); world = camera
    # turned about x: y up, scene at negative z
    z = 0.5 + 0.01 * 40
    assert v["z"][0] == pytest.approx(-z)
    assert v["x"][0] == pytest.approx(rays[0, 40, 0] * z, rel=1e-6)
    assert v["y"][0] == pytest.approx(-rays[0, 40, 1] * z, rel=1e-6)
    # the top image row is higher in the world than the bottom one
    assert v["y"][0] > v["y"][-1]
    # stretched so the 99th percentile of the brightest channel is white: red reaches
    # 3 * 79 = 237 in the right half (x 16 in 12 bits), same colours for both depths
    top = np.percentile(np.maximum(np.arange(40, 80) * 3, 200) * top, 99) / top
    expected = [c * 255 / top for c in (120, 0, 200)]
    got = [int(v[c][0]) for c in ("red", "green", "blue")]
    np.testing.assert_allclose(got, expected, atol=1.5)  # truncation + float32
    assert v["red"].max() >= 254  # the top 1 % saturate


def test_ply_depth_colours_are_visible(tmp_path, rig):
    sink = PlyExportSink(tmp_path / "ply", rig)
    result = make_result(rig)
    result.frame.image[...] = 3  # a near-black camera image
    sink.write(result, RunStats())
    v = read_ply(tmp_path / "ply" / "000007.ply")
    rgb = np.stack([v["red"], v["green"], v["blue"]], axis=1).astype(int)
    assert np.all(rgb.max(axis=1) >= 48)  # no near-black point
    near, far = rgb[np.argmax(v["z"])], rgb[np.argmin(v["z"])]  # z is negative
    assert near[2] > near[0] and far[0] > far[2]  # turbo: near blue, far red


def enospc_after(monkeypatch, n_bytes):
    """Make writes of export files fail with ENOSPC after ``n_bytes`` (a full disk)."""
    import builtins
    import errno

    real_open = builtins.open

    class Full:
        def __init__(self, fh):
            self.fh, self.left = fh, n_bytes

        def write(self, data):
            size = memoryview(data).nbytes
            if size > self.left:
                self.fh.write(bytes(memoryview(data).cast("B")[: self.left]))
                self.left = 0
                raise OSError(errno.ENOSPC, "No space left on device")
            self.left -= size
            return self.fh.write(data)

        def __getattr__(self, name):
            return getattr(self.fh, name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.fh.close()

    def fake_open(file, mode="r", *args, **kwargs):
        fh = real_open(file, mode, *args, **kwargs)
        return Full(fh) if "w" in mode and str(file).endswith(".tmp") else fh

    monkeypatch.setattr(builtins, "open", fake_open)


@pytest.mark.parametrize("kind", ["depth", "ply"])
def test_full_disk_one_error_no_partial_files(tmp_path, rig, monkeypatch, kind):
    out = tmp_path / kind
    sink = DepthExportSink(out) if kind == "depth" else PlyExportSink(out, rig)
    sink.write(make_result(rig, index=1), RunStats())
    enospc_after(monkeypatch, 1000)
    with pytest.raises(OutputError) as err:
        sink.write(make_result(rig, index=2), RunStats())
    suffix = ".npy" if kind == "depth" else ".ply"
    assert str(err.value) == f"{out}/000002{suffix}: cannot write: No space left on device"
    assert sorted(p.name for p in out.iterdir()) == [f"000001{suffix}"]  # complete files only


def test_recorder_sink(tmp_path, rig):
    sink = RecorderSink(tmp_path / "rec", rig, 0.02)
    results = [make_result(rig, index=i) for i in range(3)]
    stats = RunStats()
    for r in results:
        sink.write(r, stats)
    sink.close()
    assert "3 frames" in sink.describe()
    rec = read_recording(tmp_path / "rec")
    assert [e.t for e in rec.frames] == pytest.approx([0, 1 / 30, 2 / 30])
    np.testing.assert_array_equal(load_frame(rec, 2), results[2].frame.image)
    assert stats.extra["recorder_dropped"] == 0
