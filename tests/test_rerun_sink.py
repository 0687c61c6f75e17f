"""Rerun sink: write an .rrd from a hand-made FrameResult and read it back; serve on loopback."""

from __future__ import annotations

import socket
from pathlib import Path

import numpy as np
import psutil
import pytest
from rerun.chunk import RrdReader

from lightflow.app.core.errors import ConfigError, DriverError
from lightflow.app.core.results import BandSet, FrameResult, RunStats
from lightflow.app.core.rig import load_rig
from lightflow.app.sinks.rerun_sink import RerunSink, lookup_u16
from lightflow.drivers.base import Frame

RIG_FILE = Path(__file__).resolve().parents[1] / "app" / "rigs" / "two-projector.json"


@pytest.fixture(scope="module")
def rig():
    return load_rig(RIG_FILE).scaled(0.25)  # 400x300, fx = 450


def make_result(rig, index: int) -> FrameResult:
    h, w = rig.camera.height, rig.camera.width
    depth = np.full((h, w), 0.8 + 0.01 * index, np.float32)  # a fronto-parallel plane
    depth[: h // 2] = np.nan  # top half: no estimate
    image = np.zeros((h, w, 3), np.uint8)
    image[..., 0] = 200
    bands = [
        BandSet(
            "red",
            rows=np.array([10, 20, 30], np.float32),
            starts=np.array([5, 6, 7], np.float32),
            ends=np.array([9, 10, 11], np.float32),
            valid=np.array([True, False, True]),
        ),
        BandSet("blue", *(np.zeros(0, np.float32) for _ in range(3)), np.zeros(0, bool)),
    ]
    grid = np.full((h // 4, w // 4), 3.0, np.float32)
    return FrameResult(
        Frame(index, 1.0 + index / 30, 0.02, image), depth, [grid, grid * 2],
        np.log(grid / (grid * 2)), bands, 4, timings_ms={"total": 9.0}, coverage=0.5,
    )  # fmt: skip


def chunks_by_entity(path: Path) -> dict[str, list]:
    out: dict[str, list] = {}
    for chunk in RrdReader(path).stream():
        out.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
    return out


def column(batches, name: str) -> list:
    return [v for rb in batches if name in rb.schema.names for v in rb.column(name).to_pylist()]


def test_rrd_round_trip(tmp_path, rig):
    path = tmp_path / "out" / "demo.rrd"
    sink = RerunSink(rig, "rrd", path=path, max_points=5000)
    for i in range(3):
        sink.write(make_result(rig, i), RunStats(fps=29.5, latency_ms=12.0, dropped=i))
    sink.close()
    sink.close()  # twice is fine
    assert sink.describe() == f"Rerun: 3 frames in {path}; open with `rerun {path}`"
    check_round_trip(path)


def check_round_trip(path):
    ent = chunks_by_entity(path)
    for name in ["/world", "/world/camera", "/world/camera/image", "/world/camera/depth",
                 "/world/camera/depth_overlay", "/world/camera/bands/red/accepted",
                 "/world/camera/bands/red/rejected", "/flow/red", "/flow/blue",
                 "/flow/log_ratio", "/world/points", "/stats/rate/fps",
                 "/stats/time_ms/latency", "/stats/time_ms/processing", "/stats/lost/dropped",
                 "/stats/coverage/depth_on_image", "/log"]:  # fmt: skip
        assert name in ent, name
    # no 3D content under the pinhole: the viewer would refuse to show it in 3D
    pinholes = [e for e, b in ent.items() if column(b, "Pinhole:image_from_camera")]
    assert pinholes == ["/world/camera"]
    assert not [e for e, b in ent.items()
                if e.startswith("/world/camera/") and column(b, "Points3D:positions")]

    K = column(ent["/world/camera"], "Pinhole:image_from_camera")[0][0]  # column-major
    assert (K[0], K[4], K[6], K[7]) == (450.0, 450.0, 199.5, 149.5)
    assert column(ent["/world/camera"], "Pinhole:resolution")[0] == [[400.0, 300.0]]

    assert sorted(column(ent["/world/camera/depth"], "frame")) == [0, 1, 2]
    fmt = column(ent["/world/camera/depth"], "DepthImage:format")[0][0]
    buf = bytes(column(ent["/world/camera/depth"], "DepthImage:buffer")[0][0])
    depth = np.frombuffer(buf, np.uint16).reshape(fmt["height"], fmt["width"])
    assert depth.shape == (300, 400)
    assert (depth[:150] == 0).all()  # no estimate is 0 for Rerun
    assert (depth[150:] == 800).all()  # millimetres
    assert column(ent["/world/camera/depth"], "DepthImage:meter")[0] == [1000.0]
    assert column(ent["/world/camera/depth"], "DepthImage:depth_range")[0] == [[400.0, 1200.0]]
    # the overlay: class 0 (transparent) without depth, else the depth's step of the range
    fmt = column(ent["/world/camera/depth_overlay"], "SegmentationImage:format")[0][0]
    buf = bytes(column(ent["/world/camera/depth_overlay"], "SegmentationImage:buffer")[0][0])
    ids = np.frombuffer(buf, np.uint8).reshape(fmt["height"], fmt["width"])
    assert (ids[:150] == 0).all()
    assert (ids[150:] == 128).all()  # 0.8 m: the middle of 0.4-1.2 m, 1 + 127 steps

    positions = column(ent["/world/points"], "Points3D:positions")
    assert [len(p) for p in positions] == [5000, 5000, 5000]  # 60000 subsampled
    assert {round(p[2], 4) for p in positions[0]} == {0.8}
    # coloured by depth: 0.8 m is mid-range of 0.4-1.2 m, turbo's green
    colors = column(ent["/world/points"], "Points3D:colors")[0]
    r, g, b = (colors[0] >> 24) & 255, (colors[0] >> 16) & 255, (colors[0] >> 8) & 255
    assert g > 200 and g > r and g > b

    accepted = column(ent["/world/camera/bands/red/accepted"], "LineStrips2D:strips")[0]
    rejected = column(ent["/world/camera/bands/red/rejected"], "LineStrips2D:strips")[0]
    assert accepted == [[[5.0, 10.0], [9.0, 10.0]], [[7.0, 30.0], [11.0, 30.0]]]
    assert rejected == [[[6.0, 20.0], [10.0, 20.0]]]
    acc_rgb = column(ent["/world/camera/bands/red/accepted"], "LineStrips2D:colors")[0]
    rej_rgb = column(ent["/world/camera/bands/red/rejected"], "LineStrips2D:colors")[0]
    assert acc_rgb != rej_rgb

    # flows: colour-mapped images on the analysis grid, fixed range 0-40 projector px
    fmt = column(ent["/flow/red"], "Image:format")[0][0]
    assert (fmt["width"], fmt["height"]) == (100, 75)

    assert column(ent["/stats/lost/dropped"], "Scalars:scalars") == [[0.0], [1.0], [2.0]]
    assert column(ent["/stats/coverage/depth_on_image"], "Scalars:scalars")[0] == [50.0]
    # the first frame's time (compilation) is a note, not a point of the time plot
    assert sorted(column(ent["/stats/time_ms/latency"], "frame")) == [1, 2]
    assert "first frame" in column(ent["/log"], "TextLog:text")[0][0]

    reader = RrdReader(path)
    assert len(reader.blueprints()) == 1


def test_rrd_compressed_image(tmp_path, rig):
    path = tmp_path / "c.rrd"
    sink = RerunSink(rig, "rrd", path=path, compress=True)
    sink.write(make_result(rig, 0), RunStats())
    sink.close()
    ent = chunks_by_entity(path)
    blob = bytes(column(ent["/world/camera/image"], "EncodedImage:blob")[0][0])
    assert blob[:2] == b"\xff\xd8"  # JPEG


def test_overlay_lookup_equals_take():
    rng = np.random.default_rng(3)
    table = rng.integers(0, 256, 65536).astype(np.uint8)
    index = rng.integers(0, 65536, (37, 53)).astype(np.uint16)
    index[0, :3] = (0, 65535, 1)
    assert np.array_equal(lookup_u16(table, index), np.take(table, index))


def test_bad_options(rig, monkeypatch):
    with pytest.raises(ConfigError, match="expected one of rrd, spawn, serve"):
        RerunSink(rig, "web")
    with pytest.raises(ConfigError, match="a path is needed"):
        RerunSink(rig, "rrd")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(DriverError, match="no display.*--rrd FILE"):
        RerunSink(rig, "spawn")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_serve_listens_on_loopback_only(rig, tmp_path):
    port = free_port()
    saved = tmp_path / "kept" / "run.rrd"
    sink = RerunSink(rig, "serve", port=port, save_path=saved)
    try:
        proc = psutil.Process(sink._process.pid)
        listening = [
            c.laddr
            for p in [proc, *proc.children(recursive=True)]
            for c in p.net_connections(kind="inet")
            if c.status == psutil.CONN_LISTEN
        ]
        assert listening and all(addr.ip == "127.0.0.1" for addr in listening)
        assert any(addr.port == port for addr in listening)
        sink.write(make_result(rig, 0), RunStats())
        assert sink.describe() == (
            f"Rerun server on 127.0.0.1:{port}: "
            f"`rerun --connect rerun+http://127.0.0.1:{port}/proxy`; saved in {saved}"
        )
    finally:
        sink.close()
    # what the server got is also kept in a file, complete once closed
    assert sorted(column(chunks_by_entity(saved)["/world/camera/depth"], "frame")) == [0]
    assert not proc.is_running() or proc.status() == psutil.STATUS_ZOMBIE


def test_a_killed_server_is_one_line_and_the_saved_file_is_complete(rig, tmp_path):
    import os
    import signal

    saved = tmp_path / "run.rrd"
    sink = RerunSink(rig, "serve", port=free_port(), save_path=saved)
    try:
        for i in range(3):
            sink.write(make_result(rig, i), RunStats())
        os.kill(sink._process.pid, signal.SIGKILL)
        sink._process.proc.wait()
        # the next frame is still saved, then the dead server is reported, once
        with pytest.raises(DriverError) as err:
            sink.write(make_result(rig, 3), RunStats())
    finally:
        sink.close()
    assert str(err.value) == f"Rerun server exited (killed by SIGKILL) (the run is in {saved})"
    assert sorted(column(chunks_by_entity(saved)["/world/camera/depth"], "frame")) == list(range(4))


CHILD = """
import resource, signal, sys
sys.path.insert(0, {tests!r})
from test_rerun_sink import make_result, RIG_FILE
from lightflow.app.core.errors import LightflowError
from lightflow.app.core.results import RunStats
from lightflow.app.core.rig import load_rig
from lightflow.app.sinks.rerun_sink import RerunSink
rig = load_rig(RIG_FILE).scaled(0.25)
mode = sys.argv[1]
if mode == "full":
    # a file size limit fails writes like a full disk (EFBIG instead of ENOSPC)
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000))
    try:
        sink = RerunSink(rig, "rrd", path=sys.argv[2])
        for i in range(10):
            sink.write(make_result(rig, i), RunStats())
        sink.close()
    except LightflowError as exc:
        print(f"lightflow: error: {{exc}}", file=sys.stderr)
        sys.exit(2)
else:
    sink = RerunSink(rig, "serve", port=int(sys.argv[2]))
    print(sink._process.pid, flush=True)
    sys.stdin.read()  # until killed
"""


def run_child(tmp_path, *args, **kwargs):
    import subprocess
    import sys

    script = tmp_path / "child.py"
    script.write_text(CHILD.format(tests=str(Path(__file__).parent)))
    return subprocess.Popen([sys.executable, str(script), *args], text=True, **kwargs)


def test_full_disk_is_one_line_and_leaves_no_file(tmp_path):
    import subprocess

    path = tmp_path / "out.rrd"
    proc = run_child(tmp_path, "full", str(path), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        out, err = proc.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        proc.kill()  # leave no child behind for later tests to trip over
        out, err = proc.communicate()
        raise AssertionError(f"a full disk hung the run; it printed: {err!r}") from None
    assert proc.returncode == 2, err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert err.startswith(f"lightflow: error: {path}: cannot write the Rerun file (")
    assert "the partial file was removed" in err
    assert not path.exists()


def test_serve_child_dies_with_a_killed_parent(tmp_path):
    import signal
    import subprocess

    port = free_port()
    parent = run_child(tmp_path, "serve", str(port), stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    try:
        server = psutil.Process(int(parent.stdout.readline()))
        assert server.is_running()
    finally:
        parent.send_signal(signal.SIGKILL)  # no cleanup code of lightflow runs
        parent.wait()
        parent.stdin.close()
        parent.stdout.close()
    try:
        server.wait(timeout=10)
    except psutil.TimeoutExpired:
        server.kill()
        raise AssertionError("the Rerun server outlived its killed parent") from None
    with socket.socket() as s:
        # free again for a new server (connections of the killed client may linger in
        # TIME_WAIT, which SO_REUSEADDR allows, as servers use it; a listener would not)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", port))
        s.listen()


def test_bands_without_flow_are_drawn_rejected(tmp_path, rig):
    """A band that passed its checks but kept no flow (a static wall) is not 'accepted'."""
    result = make_result(rig, 0)
    result.flows_grid[0][30 // 4, :] = np.nan  # the cell row of the band at y = 30
    path = tmp_path / "b.rrd"
    sink = RerunSink(rig, "rrd", path=path)
    sink.write(result, RunStats())
    sink.close()
    ent = chunks_by_entity(path)
    accepted = column(ent["/world/camera/bands/red/accepted"], "LineStrips2D:strips")[0]
    rejected = column(ent["/world/camera/bands/red/rejected"], "LineStrips2D:strips")[0]
    assert accepted == [[[5.0, 10.0], [9.0, 10.0]]]
    assert rejected == [[[6.0, 20.0], [10.0, 20.0]], [[7.0, 30.0], [11.0, 30.0]]]
