"""The depth sink's .rrd as a user sees it: opened in the real Rerun viewer, headless.

The viewer renders on Mesa's software Vulkan (lavapipe, apt package
``mesa-vulkan-drivers``); no display is needed.  It is started here bound to
127.0.0.1, in its own process group, and killed as a group.

Set ``LIGHTFLOW_SHOTS=DIR`` to keep the screenshots.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
from pathlib import Path

import cv2
import numpy as np
import psutil
import pytest
from rerun.experimental import ViewerClient
from test_rerun_sink import chunks_by_entity, column

from lightflow.app.core.causes import DEPTH, NO_LINES, STATIC, count_causes
from lightflow.app.core.errors import OutputClosed
from lightflow.app.core.results import BandSet, FrameResult, RunStats
from lightflow.app.core.rig import load_rig
from lightflow.app.sinks.rerun_sink import RerunSink, disable_viewer_analytics, rerun_binary
from lightflow.drivers.base import Frame

RIG_FILE = Path(__file__).resolve().parents[1] / "app" / "rigs" / "two-projector.json"
LAVAPIPE_ICD = Path("/usr/share/vulkan/icd.d/lvp_icd.x86_64.json")
FRAMES = 5


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def disc_result(rig, index: int) -> FrameResult:
    """A tilted disc moving right in front of nothing: depth 0.55-0.85 m, flows, bands."""
    h, w = rig.camera.height, rig.camera.width
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    cx = w / 2 + 8 * index
    disc = (xx - cx) ** 2 + (yy - h / 2) ** 2 < (0.3 * h) ** 2
    # the depth on the analysis grid (cell centres), upsampled by the result as the
    # pipeline's is
    gy, gx = yy[1::4, 1::4] + 0.5, xx[1::4, 1::4] + 0.5
    on_grid = (gx - cx) ** 2 + (gy - h / 2) ** 2 < (0.3 * h) ** 2
    depth_grid = np.where(on_grid, 0.7 + 0.3 * (gx - cx) / w, np.nan).astype(np.float32)
    image = np.full((h, w, 3), 50, np.uint8)
    image[disc] = (190, 150, 120)
    rows = np.arange(4, h, 6, dtype=np.float32)
    on_disc = np.abs(rows - h / 2) < 0.25 * h
    bands = [
        BandSet("red", rows, np.full_like(rows, cx - 20), np.full_like(rows, cx - 5), on_disc),
        BandSet("blue", rows, np.full_like(rows, cx + 5), np.full_like(rows, cx + 14), on_disc),
    ]
    grid = np.where(disc[2::4, 2::4], 14.0, np.nan).astype(np.float32)
    # depth on the disc; around it a static wall, and no lines in its shadow on the right
    causes_grid = np.where(disc[2::4, 2::4], DEPTH, STATIC).astype(np.uint8)
    causes_grid[:, -causes_grid.shape[1] // 5:] = NO_LINES
    return FrameResult(
        Frame(index, 1.0 + index / 30, 0.02, image), None, [grid, grid * 0.5],
        np.log(grid / (grid * 0.5)), bands, 4,
        timings_ms={"total": 30_000.0 if index == 0 else 40.0 + index},
        coverage=float(disc.mean()),
        depth_std_grid=np.where(disc, 0.004 + 0.02 * np.abs(xx - cx) / w,
                                np.nan)[2::4, 2::4].astype(np.float32),
        causes_grid=causes_grid,
        cause_counts=count_causes(causes_grid),
        depth_grid=depth_grid,
        full_size=(w, h),
    )  # fmt: skip


@pytest.fixture(scope="module")
def rrd(tmp_path_factory):
    rig = load_rig(RIG_FILE).scaled(0.25)
    path = tmp_path_factory.mktemp("viewer") / "run.rrd"
    sink = RerunSink(rig, "rrd", path=path, compress=True)
    for i in range(FRAMES):
        stats = RunStats(frames_done=i + 1, fps=0.0 if i == 0 else 29.0, dropped=i // 3,
                         latency_ms=31_000.0 if i == 0 else 60.0, mib_per_s=3.0)
        sink.write(disc_result(rig, i), stats)
    sink.close()
    return path


@pytest.fixture(scope="module")
def viewer():
    if not LAVAPIPE_ICD.exists():
        pytest.fail(f"no software Vulkan ({LAVAPIPE_ICD}): apt-get install mesa-vulkan-drivers")
    disable_viewer_analytics()
    port = free_port()
    log = open(os.devnull, "wb")  # noqa: SIM115
    proc = subprocess.Popen(
        [str(rerun_binary()), "--headless", "--hide-welcome-screen",
         "--bind", "127.0.0.1", "--port", str(port)],
        stdin=subprocess.DEVNULL, stdout=log, stderr=log, start_new_session=True,
    )  # fmt: skip
    log.close()
    try:
        client = None
        url = f"rerun+http://127.0.0.1:{port}/proxy"
        for _ in range(60):  # the gRPC server comes up within seconds; each try blocks
            assert proc.poll() is None, "the headless viewer exited"
            try:
                client = ViewerClient.connect(url)
                client.get_state()
                break
            except (ConnectionError, RuntimeError):
                client = None
                proc_wait(proc, 0.5)
        assert client is not None, "the headless viewer did not answer"
        yield proc, client
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def proc_wait(proc, seconds: float) -> None:
    """Wait for the viewer to exit or ``seconds`` to pass (it should not exit)."""
    try:
        proc.wait(timeout=seconds)
    except subprocess.TimeoutExpired:
        pass


def coloured_pixels(png: bytes) -> int:
    """Pixels of a screenshot with a clear hue: UI and grid are grey, the points are turbo."""
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    return int(np.count_nonzero(img.max(axis=2).astype(int) - img.min(axis=2) > 80))


def test_viewer_shows_every_panel(rrd, viewer):
    proc, client = viewer
    listening = [
        c.laddr for p in [psutil.Process(proc.pid), *psutil.Process(proc.pid).children(True)]
        for c in p.net_connections(kind="inet") if c.status == psutil.CONN_LISTEN
    ]  # fmt: skip
    assert listening and all(a.ip == "127.0.0.1" for a in listening), listening

    opened = client.open(str(rrd))
    assert len(opened.store_ids) == 1
    client.set_time("frame", sequence=FRAMES - 1, play_state="paused")
    for _ in range(50):
        state = client.get_state()
        if not state.loading:
            break
        client.take_screenshot(max_size=64)  # blocks for one paint: paces the loop
    assert not state.loading

    views = {v.name: v for v in state.views}
    kinds = sorted(v.view_class for v in state.views)
    assert kinds.count("3D") == 1 and kinds.count("TimeSeries") == 5
    assert not [(v.name, v.reports) for v in state.views if v.reports]
    view3d = next(v for v in views.values() if v.view_class == "3D")
    camera = next(v for v in views.values() if v.name.startswith("camera + depth"))

    # the first paints may come before the data: take screenshots until the points show
    for _ in range(10):
        shot3d = client.take_screenshot(view3d.view_id)
        if coloured_pixels(shot3d) > 500:
            break
    shot2d = client.take_screenshot(camera.view_id)
    shots = os.environ.get("LIGHTFLOW_SHOTS")
    if shots:
        Path(shots).mkdir(parents=True, exist_ok=True)
        Path(shots, "viewer-3d.png").write_bytes(shot3d)
        Path(shots, "viewer-camera-depth.png").write_bytes(shot2d)
        client.save_screenshot(str(Path(shots, "viewer-all.png").resolve()))
    # measured: about 6000 coloured pixels of points in the 3D view, 30 000 in 2D
    assert coloured_pixels(shot3d) > 500
    assert coloured_pixels(shot2d) > 5000
    # the reports of views just painted (the first state may predate the paint)
    state = client.get_state()
    assert not [(v.name, v.reports) for v in state.views if v.reports]


def test_rerun_binary_present():
    assert shutil.which(str(rerun_binary())), rerun_binary()


@pytest.fixture
def spawned(tmp_path, monkeypatch):
    """A RerunSink on a real (windowed) viewer it spawned on a private Xvfb, saving to
    ``kept.rrd``: ``(rig, sink, port, saved)``; the viewer and the X server are stopped
    afterwards (the viewer outlives a sink by design; not a test)."""
    from xserver import start_xvfb

    if not LAVAPIPE_ICD.exists():
        pytest.fail(f"no software Vulkan ({LAVAPIPE_ICD}): apt-get install mesa-vulkan-drivers")
    rig = load_rig(RIG_FILE).scaled(0.25)
    server = start_xvfb(tmp_path, 1280, 800)
    sink = None
    try:
        monkeypatch.setenv("DISPLAY", server.display)
        # a fresh per-user Rerun config: analytics must be switched off by lightflow itself
        monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "config"))
        port = free_port()
        saved = tmp_path / "kept.rrd"
        sink = RerunSink(rig, "spawn", port=port, save_path=saved)
        yield rig, sink, port, saved
    finally:
        if sink is not None and sink._process is not None:
            sink._process.stop()
        server.stop()


def test_spawned_viewer_is_on_loopback_and_shows_the_run(spawned, tmp_path):
    """``--spawn``: the real (windowed) viewer on Xvfb gets every frame, listens on 127.0.0.1."""
    rig, sink, port, saved = spawned
    viewer = psutil.Process(sink._process.pid)
    for i in range(3):
        sink.write(disc_result(rig, i), RunStats(frames_done=i + 1))
    sink.close()
    listening = [
        c.laddr for p in [viewer, *viewer.children(True)]
        for c in p.net_connections(kind="inet") if c.status == psutil.CONN_LISTEN
    ]  # fmt: skip
    assert listening and all(a.ip == "127.0.0.1" for a in listening), listening
    client = ViewerClient.connect(f"rerun+http://127.0.0.1:{port}/proxy")
    for _ in range(50):
        state = client.get_state()
        if state.recordings and not state.loading:
            break
        client.take_screenshot(max_size=64)  # blocks for one paint: paces the loop
    [recording] = state.recordings
    frame = next(t for t in recording.timelines if t.name == "frame")
    assert (frame.start, frame.end) == (0, 2)
    assert len(state.views) == 16
    client.take_screenshot(max_size=256)  # every view painted once: reports are current
    state = client.get_state()
    assert not [(v.name, v.reports) for v in state.views if v.reports]
    assert saved.stat().st_size > 0  # and the run is kept in a file too
    config = json.loads((tmp_path / "config/rerun/analytics.json").read_text())
    assert config["analytics_enabled"] is False


def test_closing_the_spawned_viewer_stops_cleanly(spawned):
    """The user quits the viewer (as its window's close button does): the next frame
    says so once (:class:`OutputClosed`, which the runner treats as Ctrl-C), closing is
    quiet, and the saved copy holds every frame logged."""
    rig, sink, port, saved = spawned
    for i in range(2):
        sink.write(disc_result(rig, i), RunStats(frames_done=i + 1))
    # the viewer's own Quit (Ctrl+Q), as a user closing it
    ViewerClient.connect(f"rerun+http://127.0.0.1:{port}/proxy").run_command("ui.quit")
    assert sink._process.proc.wait(timeout=30) == 0
    with pytest.raises(OutputClosed) as closed:
        sink.write(disc_result(rig, 2), RunStats(frames_done=3))
    assert str(closed.value) == f"the Rerun viewer was closed (the run is in {saved})"
    sink.close()  # quiet: already reported
    frames = sorted(column(chunks_by_entity(saved)["/world/camera/depth"], "frame"))
    assert frames == [0, 1, 2]
