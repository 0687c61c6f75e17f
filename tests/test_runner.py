"""Runner: drop-oldest counting, lossless mode, camera gaps, errors from each thread, sinks."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from lightflow.app.cameras import open_camera
from lightflow.app.core.errors import DeviceLostError, DriverError, FrameError, OutputClosed
from lightflow.app.core.pipeline import DepthPipeline, PipelineConfig
from lightflow.app.core.results import BandSet, RunStats
from lightflow.app.core.rig import load_rig
from lightflow.app.exposure import BlurAwareExposure, measure_bands, settle_exposure
from lightflow.app.runner import DropOldestQueue, RateMeter, Runner
from lightflow.app.status import StatusLine, format_status, format_summary
from lightflow.drivers.base import Camera, Frame
from lightflow.drivers.sim.synthetic import SensorModel, SyntheticCamera

RIG_FILE = Path(__file__).resolve().parents[1] / "app" / "rigs" / "two-projector.json"
WAIT_S = 60.0


@pytest.fixture(scope="module")
def rig():
    return load_rig(RIG_FILE).scaled(0.25)


@pytest.fixture(scope="module")
def image(rig):
    cam = SyntheticCamera(rig, "board", frames=1, sensor=SensorModel(samples=4))
    with cam:
        return next(iter(cam.frames())).image


@pytest.fixture(scope="module")
def pipeline(rig):
    return DepthPipeline(rig, PipelineConfig())


class ListCamera(Camera):
    """A camera that yields the given images with the given indices, as fast as it can.

    ``indices=None`` with ``endless=True`` yields until :meth:`stop`;
    ``fail_with`` is raised after the last image (like an unplugged camera).
    """

    uri = "test:list"

    def __init__(self, images, indices=None, fail_with=None, endless=False):
        self.images = images
        self.indices = indices if indices is not None else list(range(len(images)))
        self.fail_with = fail_with
        self.endless = endless
        self.exhausted = threading.Event()
        self._stop = threading.Event()
        self.stop_calls = 0

    def open(self):
        self._stop.clear()

    def close(self):
        pass

    @property
    def size(self):
        return self.images[0].shape[1], self.images[0].shape[0]

    @property
    def exposure_s(self):
        return 0.02

    def set_exposure(self, seconds):
        return 0.02

    def stop(self):
        self.stop_calls += 1
        self._stop.set()

    def stats(self):
        return {"underruns": 3.0}

    def frames(self) -> Iterator[Frame]:
        try:
            k = 0
            while not self._stop.is_set():
                if k >= len(self.indices):
                    if not self.endless:
                        break
                    self.indices.append(self.indices[-1] + 1)
                i = self.indices[k]
                yield Frame(i, i / 30, 0.02, self.images[k % len(self.images)], f"{i:06d}")
                k += 1
            if self.fail_with is not None:
                raise self.fail_with
        finally:
            self.exhausted.set()


class ListSink:
    """Collects frame indices; may block on an Event or fail on a given write or on close."""

    def __init__(self, gate: threading.Event | None = None, fail_at=None, fail_close=None,
                 fail_with=None):  # fmt: skip
        self.gate = gate
        self.fail_at = fail_at
        self.fail_close = fail_close
        self.fail_with = fail_with or DriverError("test sink: disk full")
        self.indices: list[int] = []
        self.stats: list[RunStats] = []
        self.closed = 0

    def write(self, result, stats):
        if self.gate is not None:
            assert self.gate.wait(WAIT_S)
        if self.fail_at is not None and len(self.indices) == self.fail_at:
            raise self.fail_with
        self.indices.append(result.frame.index)
        self.stats.append(stats)
        assert result.depth.shape == (300, 400)

    def close(self):
        self.closed += 1
        if self.fail_close is not None:
            raise self.fail_close


def test_queue_drops_oldest_and_counts():
    q = DropOldestQueue(2)
    for i in range(5):
        assert q.put(i)
    assert q.dropped == 3
    q.put_end()
    assert [q.get(), q.get()] == [3, 4]
    q.abort()
    assert not q.put(9)


def test_slow_sink_drops_oldest(image, pipeline):
    cam = ListCamera([image] * 20)
    slow = ListSink(gate=cam.exhausted)  # blocks until the camera has delivered everything
    with cam:
        stats = Runner(cam, pipeline, [slow], queue_size=2).run(threading.Event())
    assert stats.frames_in == 20
    assert stats.dropped > 0
    e = stats.extra
    assert e["dropped_frames_queue"] + e["dropped_results_queue"] == stats.dropped
    assert stats.frames_done + stats.dropped == 20
    assert slow.indices == sorted(slow.indices)
    assert slow.indices[-1] == 19  # the newest frame is never the one dropped
    assert len(slow.indices) == stats.frames_done
    assert slow.closed == 1
    assert e["camera_underruns"] == 3.0
    assert stats.latency_ms > 0 and stats.fps > 0
    # 20 frames handed over at once span far less than RATE_MIN_SPAN_S: no data rate
    # (usually 0; a preempted capture thread may span enough, and then it is a real one)
    assert stats.mib_per_s < 1e4


def test_rate_meter_is_not_fooled_by_a_burst():
    # a replay's read-ahead: 4 frames of 1 MiB within 40 µs, then 30 frames/s
    meter = RateMeter(window_s=1.0, min_span_s=0.25)
    rates = [meter.add(i * 1e-5, 2**20) for i in range(4)]
    assert rates == [0.0] * 4  # a burst is no rate
    for i in range(1, 91):
        rate = meter.add(i / 30, 2**20)
    assert rate == pytest.approx(30.0, rel=1e-9)  # the burst has left the window
    # a stall: the rate falls to what arrived over the last second
    assert meter.add(3.0 + 2.0, 2**20) == pytest.approx(1 / 2.0)


def test_lossless_blocks_instead_of_dropping(image, pipeline):
    cam = ListCamera([image] * 12)
    slow = ListSink(gate=threading.Event())
    seen: list[RunStats] = []
    runner = Runner(cam, pipeline, [slow], queue_size=2, lossless=True, on_stats=seen.append)
    stop = threading.Event()
    with cam:
        runner.start(stop)
        assert not cam.exhausted.wait(0.5)  # the blocked sink holds the camera back
        slow.gate.set()
        stats = runner.join()
    assert slow.indices == list(range(12))
    assert stats.dropped == 0 and stats.frames_done == 12
    assert [s.frames_done for s in seen] == list(range(1, 13))
    assert stop.is_set() and not runner.stopped  # set because the run ended, not by the user


def test_camera_gaps_are_counted(image, pipeline):
    cam = ListCamera([image] * 5, indices=[0, 1, 2, 5, 6])
    sink = ListSink()
    with cam:
        stats = Runner(cam, pipeline, [sink], lossless=True).run()
    assert stats.camera_lost == 2
    assert sink.indices == [0, 1, 2, 5, 6]


def test_device_lost_drains_and_closes(image, pipeline):
    lost = DeviceLostError("aravis:127.0.0.1: camera lost after 5 frames (no answer)")
    cam = ListCamera([image] * 5, fail_with=lost)
    sinks = [ListSink(), ListSink()]
    runner = Runner(cam, pipeline, sinks, lossless=True)
    with cam, pytest.raises(DeviceLostError) as info:
        runner.run()
    assert info.value is lost
    for s in sinks:
        assert s.indices == [0, 1, 2, 3, 4] and s.closed == 1


def test_processing_error_stops_camera(image, pipeline):
    small = np.zeros((10, 10, 3), np.uint8)
    cam = ListCamera([image, image, small, image], endless=True)
    sink = ListSink()
    with cam, pytest.raises(FrameError, match="frame 000002: 10x10, expected 400x300"):
        Runner(cam, pipeline, [sink], lossless=True).run()
    assert cam.exhausted.is_set() and cam.stop_calls >= 1
    assert sink.indices == [0, 1] and sink.closed == 1


def test_sink_error_stops_everything_and_closes_each_sink_once(image, pipeline):
    cam = ListCamera([image], endless=True)
    bad, good = ListSink(fail_at=3), ListSink()
    with cam, pytest.raises(DriverError, match="test sink: disk full"):
        Runner(cam, pipeline, [bad, good]).run()
    assert cam.exhausted.is_set()
    assert bad.closed == 1 and good.closed == 1
    assert len(bad.indices) == 3 and bad.indices == sorted(bad.indices)  # live: drops happen


def test_close_error_is_raised_and_other_sinks_still_close(image, pipeline):
    cam = ListCamera([image] * 2)
    failing = ListSink(fail_close=DriverError("Rerun viewer exited: gone"))
    other = ListSink()
    with cam, pytest.raises(DriverError, match="viewer exited"):
        Runner(cam, pipeline, [failing, other]).run()
    assert failing.closed == 1 and other.closed == 1


def test_a_closed_viewer_stops_the_run_like_ctrl_c(image, pipeline):
    cam = ListCamera([image], endless=True)
    viewer = ListSink(fail_at=3, fail_with=OutputClosed("the Rerun viewer was closed"))
    other = ListSink()
    runner = Runner(cam, pipeline, [viewer, other])
    with cam:
        runner.run()  # no error: a user's stop
    assert runner.stopped and runner.closed_output == "the Rerun viewer was closed"
    assert len(viewer.indices) == 3 and viewer.closed == 1
    # the results already under way still reach the other outputs, in order
    assert len(other.indices) >= 4 and other.indices == sorted(other.indices)
    assert other.closed == 1


def test_a_viewer_closed_during_the_last_frames_is_no_error(image, pipeline):
    cam = ListCamera([image] * 2)
    viewer = ListSink(fail_close=OutputClosed("the Rerun viewer was closed"))
    runner = Runner(cam, pipeline, [viewer])
    with cam:
        runner.run()
    assert runner.closed_output == "the Rerun viewer was closed" and not runner.stopped


def test_stop_from_outside_with_main_thread_busy(image, pipeline):
    cam = ListCamera([image], endless=True)
    sink = ListSink()
    stop = threading.Event()
    runner = Runner(cam, pipeline, [sink], on_stats=lambda s: s.frames_done >= 3 and stop.set())
    with cam:
        runner.start(stop)
        assert stop.wait(WAIT_S)  # the main thread would be in pyglet meanwhile
        stats = runner.join()
    assert runner.stopped and stats.frames_done >= 3 and sink.closed == 1


def test_max_frames(image, pipeline):
    cam = ListCamera([image], endless=True)
    sink = ListSink()
    with cam:
        stats = Runner(cam, pipeline, [sink], lossless=True, max_frames=4).run()
    assert sink.indices == [0, 1, 2, 3] and stats.frames_in == 4


def test_status_line_and_summary():
    import io

    stats = RunStats(frames_in=10, frames_done=8, dropped=2, camera_lost=1, fps=29.5,
                     latency_ms=41.0, mib_per_s=12.5,
                     extra={"dropped_frames_queue": 2.0, "dropped_results_queue": 0.0,
                            "coverage": 0.4, "camera_underruns": 5.0})  # fmt: skip
    text = format_status(stats, total=10)
    for part in ["frame 8/10", "29.5 fps", "12.5 MiB/s", "latency   41 ms", "depth on image  40%",
                 "drops 2 frames/0 results", "camera lost 1", "underruns 5"]:  # fmt: skip
        assert part in text, (part, text)
    out = io.StringIO()  # not a TTY: whole lines, throttled
    line = StatusLine(out, total=10, interval_s=100.0)
    line.update(stats)
    line.update(stats)
    assert out.getvalue().count("\n") == 1
    line.finish(stats, ["rec/frames/000003.png: frame file missing (listed as frames[3])"])
    summary = format_summary(stats, ["x"])
    assert summary[0].startswith("processed 8 of 10 frames; dropped 2")
    assert "bad frames 1" in summary[0]
    assert "depth on image (share of all camera pixels with a depth, last frame): 40.0%" in summary
    assert "frame file missing" in out.getvalue()


def test_a_live_run_that_skipped_frames_is_told_of_the_faster_grid():
    from lightflow.app.status import describe_speed

    def run(skipped, later=0):
        return RunStats(frames_in=300, frames_done=300 - skipped, dropped=skipped + later,
                        extra={"dropped_frames_queue": float(skipped),
                               "dropped_results_queue": float(later)})  # fmt: skip

    assert describe_speed(run(148), 4) == (
        "depth kept up with 152 of 300 frames (the pipeline skipped the others, counted "
        "above as the frames queue's); --stride 8 takes about half the CPU of stride 4 per "
        "frame, for the same accuracy and a little less coverage (see --help)")  # fmt: skip
    assert describe_speed(run(148), 8).endswith("frames queue's)")  # no faster grid to offer
    assert describe_speed(run(20), 4) is None
    # outputs that fell behind are not the pipeline's doing
    assert describe_speed(run(0, later=100), 4) is None
    assert describe_speed(RunStats(), 4) is None


def test_open_camera_uris(rig, tmp_path):
    from lightflow.app.core.errors import ConfigError

    cam = open_camera("synthetic:ball", rig, frames=2, fps=60.0)
    assert isinstance(cam, SyntheticCamera) and cam.n_frames == 2 and cam.fps == 60.0
    assert open_camera("synthetic:ball", rig, frames=None).n_frames is None
    assert open_camera("v4l2:/dev/video7").path == "/dev/video7"
    assert open_camera("aravis:127.0.0.1").device == "127.0.0.1"
    with pytest.raises(ConfigError, match=r"camera 'gige:1': unknown camera URI .*aravis:"):
        open_camera("gige:1")
    with pytest.raises(ConfigError, match="needs a rig"):
        open_camera("synthetic:fan")
    with pytest.raises(ConfigError, match="option 'fps' does not apply"):
        open_camera("v4l2:/dev/video0", fps=3)
    with pytest.raises(ConfigError, match="not a recording folder"):
        open_camera(f"replay:{tmp_path}/none")


def test_measure_bands_fraction():
    # two rows of bands 4 px long every 10 px: 0.4 of the interval
    starts = np.concatenate([np.arange(0, 300, 10), np.arange(0, 300, 10)]).astype(np.float32)
    rows = np.repeat([0.0, 2.0], 30).astype(np.float32)
    b = BandSet("red", rows, starts, starts + 4, np.ones(60, bool))
    m = measure_bands(b)
    assert m.fraction == pytest.approx(0.4) and m.length_px == pytest.approx(4.0)
    assert m.interval_px == pytest.approx(10.0) and m.pairs == 58


def test_auto_exposure_settles_on_synthetic_camera(rig, pipeline):
    # start far too short: the bands are barely longer than the static lines
    cam = SyntheticCamera(rig, "board", frames=None, exposure_s=0.004,
                          sensor=SensorModel(samples=8))  # fmt: skip
    controller = BlurAwareExposure()
    lines: list[str] = []
    with cam:
        chosen, decisions = settle_exposure(cam, pipeline, controller, max_frames=12,
                                            log=lines.append)  # fmt: skip
    assert chosen == cam.exposure_s and chosen > 0.008
    first = decisions[0]
    assert first.changed and first.exposure_s > first.previous_s
    assert "too short, exposure 4 -> " in first.reason and "of the interval" in first.reason
    last = decisions[-1]
    lo, hi = controller.band
    assert not last.changed and lo <= last.fraction <= hi
    assert "in the best range" in last.reason
    assert len(lines) == len(decisions)


class _Result:
    """The least a sink needs from a result here: ``frame.index``."""

    def __init__(self, index):
        self.frame = Frame(index=index, timestamp=float(index), exposure_s=0.01,
                           image=np.zeros((2, 2), np.uint8))  # fmt: skip


class OrderSink:
    """Records indices; waits on ``gate`` before each write; may fail at one write."""

    def __init__(self, gate=None, fail_at=None):
        self.gate, self.fail_at = gate, fail_at
        self.indices: list[int] = []
        self.threads: set[str] = set()
        self.closed = 0

    def write(self, result, stats):
        if self.gate is not None:
            assert self.gate.wait(WAIT_S)
        if self.fail_at is not None and result.frame.index == self.fail_at:
            raise DriverError("test sink: disk full")
        self.threads.add(threading.current_thread().name)
        self.indices.append(result.frame.index)

    def close(self):
        self.closed += 1


def test_background_sink_blocking_keeps_every_result_in_order():
    from lightflow.app.sinks.background import BackgroundSink

    inner = OrderSink()
    sink = BackgroundSink(inner, maxsize=2, block=True)
    for i in range(50):
        sink.write(_Result(i), RunStats())
    sink.close()
    assert inner.indices == list(range(50))
    assert sink.dropped == 0 and sink.written == 50 and inner.closed == 1
    assert inner.threads == {"lightflow-sink-OrderSink"}  # never the caller's thread


def test_background_sink_non_blocking_counts_what_it_skips():
    from lightflow.app.sinks.background import BackgroundSink

    gate = threading.Event()
    inner = OrderSink(gate=gate)
    sink = BackgroundSink(inner, maxsize=3, block=False)
    stats = RunStats()
    for i in range(20):  # the writer is held by the gate: at most 1 in hand + 3 queued survive
        sink.write(_Result(i), stats)
    gate.set()
    sink.close()
    assert len(inner.indices) + sink.dropped == 20
    assert sink.dropped >= 16
    assert inner.indices == sorted(inner.indices) and inner.indices[-1] == 19
    assert stats.extra["dropped_sink_OrderSink"] == sink.dropped
    assert "SKIPPED" in sink.describe()


def test_background_sink_error_reaches_the_caller():
    from lightflow.app.sinks.background import BackgroundSink

    inner = OrderSink(fail_at=3)
    sink = BackgroundSink(inner, maxsize=2)
    with pytest.raises(DriverError, match="disk full"):
        for i in range(100):
            sink.write(_Result(i), RunStats())
        sink.close()
    assert inner.indices == [0, 1, 2]
    with pytest.raises(DriverError):
        sink.close()
    assert inner.closed == 1


@pytest.fixture(scope="module")
def small_recording(rig, tmp_path_factory):
    from lightflow.app.recording import RecordingWriter

    root = tmp_path_factory.mktemp("rec") / "rec"
    cam = SyntheticCamera(rig, "board", frames=9, sensor=SensorModel(samples=1))
    with cam, RecordingWriter(root, rig, cam.exposure_s) as writer:
        for frame in cam.frames():
            writer.write(frame)
    return root


@pytest.mark.parametrize("read_ahead", [1, 4])
def test_replay_read_ahead_keeps_order_and_pixels(small_recording, read_ahead):
    from lightflow.app.replay_camera import RecordedCamera

    def replay(n):
        cam = RecordedCamera(small_recording, read_ahead=n)
        with cam:
            return [(f.index, f.name, f.image) for f in cam.frames()]

    plain, ahead = replay(0), replay(read_ahead)
    assert [(i, n) for i, n, _ in ahead] == [(i, n) for i, n, _ in plain]
    assert len(plain) == 9
    for (_, _, a), (_, _, b) in zip(plain, ahead, strict=True):
        np.testing.assert_array_equal(a, b)


def test_replay_read_ahead_ends_its_reader_when_the_consumer_stops(small_recording):
    from lightflow.app.replay_camera import RecordedCamera

    cam = RecordedCamera(small_recording, loop=True, read_ahead=2)
    with cam:
        frames = cam.frames()
        got = [next(frames).index for _ in range(12)]  # more than one lap
        frames.close()
    assert got == list(range(12))
    assert not any(t.name == "lightflow-replay-reader" for t in threading.enumerate())
