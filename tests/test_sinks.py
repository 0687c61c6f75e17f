"""File sinks: depth .npy export, PLY export, recorder sink."""

from __future__ import annotations

import errno
from pathlib import Path

import numpy as np
import pytest

from lightflow.app.core.geometry import camera_rays
from lightflow.app.core.results import FrameResult, RunStats
from lightflow.app.core.rig import load_rig
from lightflow.app.recording import load_frame, read_recording
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


def test_depth_files_are_those_of_np_save_with_or_without_o_direct(tmp_path, monkeypatch):
    """The page-cache bypass writes the very bytes np.save does; a refusal falls back."""
    import os

    from lightflow.app.sinks.depth_export import DirectNpyWriter

    # the repository's own disk: /tmp may be a tmpfs, which refuses O_DIRECT
    out = Path(__file__).parent / f".direct-{os.getpid()}"
    out.mkdir()
    try:
        depth = np.random.default_rng(1).random((120, 170)).astype(np.float32)
        depth[5:9, 3:40] = np.nan
        writer = DirectNpyWriter()
        for i in range(2):  # the buffer is reused
            writer.write(out / f"{i}.npy", depth * (i + 1))
            np.save(out / f"ref{i}.npy", depth * (i + 1))
            assert (out / f"{i}.npy").read_bytes() == (out / f"ref{i}.npy").read_bytes()
        assert sorted(p.name for p in out.iterdir()) == ["0.npy", "1.npy", "ref0.npy", "ref1.npy"]
    finally:
        for p in out.iterdir():
            p.unlink()
        out.rmdir()

    real_open = os.open

    def no_direct(path, flags, *args):
        if flags & os.O_DIRECT:
            raise OSError(errno.EINVAL, "Invalid argument")
        return real_open(path, flags, *args)

    monkeypatch.setattr("os.open", no_direct)
    writer = DirectNpyWriter()
    writer.write(tmp_path / "a.npy", depth)
    assert not writer.direct
    np.save(tmp_path / "ref.npy", depth)
    assert (tmp_path / "a.npy").read_bytes() == (tmp_path / "ref.npy").read_bytes()


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


def test_ply_export(tmp_path, rig):
    sink = PlyExportSink(tmp_path / "ply", rig)
    result = make_result(rig)
    sink.write(result, RunStats())
    sink.close()
    v = read_ply(tmp_path / "ply" / "000007.ply")
    assert len(v) == 60 * 40  # every pixel with a depth
    rays = camera_rays(rig.camera)
    # first point: row 0, column 40 (row-major order of the valid pixels), in the
    # PLY frame: x right, y up, z towards the camera
    z = 0.5 + 0.01 * 40
    assert v["z"][0] == pytest.approx(-z)
    assert v["x"][0] == pytest.approx(rays[0, 40, 0] * z, rel=1e-6)
    assert v["y"][0] == pytest.approx(-rays[0, 40, 1] * z, rel=1e-6)
    last = v[-1]  # row 59, column 79
    assert last["z"] == pytest.approx(-(0.5 + 0.79))
    # coloured by depth (turbo): near and far differ, and neither is near-black
    near = np.array([v["red"][0], v["green"][0], v["blue"][0]], float)
    far = np.array([last["red"], last["green"], last["blue"]], float)
    assert near.max() > 100 and far.max() > 100
    assert np.abs(near - far).max() > 100


def test_image_to_rgb8_uses_the_significant_bits():
    from lightflow.app.sinks.ply import image_to_rgb8

    twelve_bit = np.full((2, 2, 3), 4095, np.uint16)
    assert image_to_rgb8(twelve_bit, 4095.0).max() == 255
    assert image_to_rgb8(twelve_bit).max() == 15  # read as 16-bit it would be nearly black


def test_full_disk_during_export_is_one_line_and_leaves_no_partial_file(tmp_path, rig,
                                                                        monkeypatch):
    from lightflow.app.core.errors import OutputError
    from lightflow.app.sinks.depth_export import DepthExportSink

    real_open = open

    def full_disk_open(path, mode="r", *args, **kwargs):
        fh = real_open(path, mode, *args, **kwargs)
        if "w" in mode and str(path).endswith(".tmp"):
            def write(data):
                raise OSError(errno.ENOSPC, "No space left on device")
            fh.write = write
        return fh

    def full_disk_write(fd, data):  # the depth maps' O_DIRECT path
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr("builtins.open", full_disk_open)
    monkeypatch.setattr("os.write", full_disk_write)
    for sink, name in ((DepthExportSink(tmp_path / "d"), "d/000007.npy"),
                       (PlyExportSink(tmp_path / "p", rig), "p/000007.ply")):
        with pytest.raises(OutputError) as err:
            sink.write(make_result(rig), RunStats())
        assert str(err.value) == f"{tmp_path / name}: cannot write: No space left on device"
        assert list((tmp_path / name).parent.iterdir()) == []


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
