"""``lightflow batch`` on a 2-worker LocalCluster on loopback: equal to a sequential replay,
one line per corrupt recording, a killed worker retried, a rerun doing no work."""

from __future__ import annotations

import json
import os
import pickle
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("distributed")

import cloudpickle  # noqa: E402 - a dependency of distributed
import psutil  # noqa: E402
from distributed import Client  # noqa: E402

from lightflow.app.batch import BatchOptions, local_cluster, run_batch  # noqa: E402
from lightflow.app.batch_bench import replicate_recording  # noqa: E402
from lightflow.app.cli import main  # noqa: E402
from lightflow.app.core.depth_model import load_or_build_lut  # noqa: E402
from lightflow.app.core.flow import FlowParams  # noqa: E402
from lightflow.app.core.pipeline import DepthPipeline, PipelineConfig  # noqa: E402
from lightflow.app.core.rig import load_rig  # noqa: E402
from lightflow.app.recording import RecordingWriter  # noqa: E402
from lightflow.app.replay_camera import RecordedCamera  # noqa: E402
from lightflow.drivers.sim.synthetic import SensorModel, SyntheticCamera  # noqa: E402

RIG_FILE = Path(__file__).resolve().parents[1] / "app" / "rigs" / "two-projector.json"
RENDERED = 4
FRAMES = 12
#: leak and windows relearnt every 3 frames, the blur model every 5, 3 frames per task: 4+
#: chunks per recording, each seeded with the state the previous ones left (the default
#: 30 would need 60+ frames)
CONFIG = PipelineConfig(crosstalk_every=3, flow=FlowParams(blur_refit_frames=5))

# the hooks below run on the workers: ship them by value (tests/ is not importable there)
cloudpickle.register_pickle_by_value(sys.modules[__name__])


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> list[Path]:
    rig = load_rig(RIG_FILE).scaled(0.25)
    base = tmp_path_factory.mktemp("recs")
    src = base / "rendered"
    cam = SyntheticCamera(rig, "board", frames=RENDERED, sensor=SensorModel(samples=8))
    with cam, RecordingWriter(src, rig, cam.exposure_s) as writer:
        for frame in cam.frames():
            assert writer.write(frame)
    # four recordings of FRAMES frames cycling through the rendered ones, each shifted
    recs = []
    for k in range(4):
        dst = replicate_recording(src, base / f"rec{k}", FRAMES + k)
        recs.append(dst)
    load_or_build_lut(rig, CONFIG.stride, CONFIG.depth_range)  # cached for the workers
    return recs


@pytest.fixture(scope="module")
def client(netns):
    with local_cluster(2, dashboard=False) as cluster, Client(cluster) as c:
        yield c


def sequential_depths(rec: Path, config: PipelineConfig) -> dict[str, np.ndarray]:
    """What a sequential replay computes: one pipeline over every frame in order."""
    camera = RecordedCamera(rec)
    pipeline = DepthPipeline(camera.rig, config)
    with camera:
        return {f.stem: pipeline.process(f).depth for f in camera.frames()}


def assert_depths_equal(out: Path, expected: dict[str, np.ndarray]) -> None:
    files = sorted(p.stem for p in out.glob("*.npy") if not p.stem.endswith("_std"))
    assert files == sorted(expected)
    for stem, depth in expected.items():
        got = np.load(out / f"{stem}.npy")
        assert got.dtype == np.float32 and got.shape == depth.shape
        assert np.array_equal(np.isnan(got), np.isnan(depth)), stem
        np.testing.assert_allclose(got, depth, rtol=1e-6, atol=1e-6, equal_nan=True)


@pytest.fixture(scope="module")
def expected(recordings) -> dict[str, dict[str, np.ndarray]]:
    return {r.name: sequential_depths(r, CONFIG) for r in recordings}


def test_batch_of_four_equals_sequential_replay(recordings, expected, client, tmp_path):
    out = tmp_path / "out"
    report = run_batch([str(r) for r in recordings], BatchOptions(out, config=CONFIG,
                       chunk_frames=3), client=client)  # fmt: skip
    assert not report.failed
    # per recording: scan, state pass, ceil(frames / 3) chunks
    assert report.tasks == sum(2 + -(-(FRAMES + k) // 3) for k in range(4))
    for r in recordings:
        assert_depths_equal(out / r.name, expected[r.name])
    # the state really differs between chunks: seeding chunk 3 with chunk 1's state would not do
    with open(out / "rec0" / ".batch" / "states.pkl", "rb") as fh:
        states = pickle.load(fh)["states"]
    assert len(states) == 3
    # (the simulated camera has no colour leak: the blur model is what changes)
    assert states[0]["flow"]["_fitted"]
    assert not np.array_equal(states[0]["flow"]["blur"], states[-1]["flow"]["blur"])
    info = json.loads((out / "batch.json").read_text())["recordings"]
    assert set(info) == {r.name for r in recordings}
    e = info["rec1"]
    assert e["status"] == "complete" and e["frames"] == e["frames_done"] == FRAMES + 1
    # per frame: the depth map and its predicted standard deviation
    assert e["bad_frames"] == [] and e["timings"]["bytes_out"] == 2 * (FRAMES + 1) * (
        300 * 400 * 4 + 128
    )


def test_rerun_does_no_work_and_resumes_a_lost_chunk(recordings, expected, client, tmp_path):
    out = tmp_path / "out"
    recs = [str(r) for r in recordings[:2]]
    options = BatchOptions(out, config=CONFIG, chunk_frames=3)
    assert run_batch(recs, options, client=client).tasks == (2 + 4) + (2 + 5)  # 12, 13 frames
    stamps = {p: p.stat().st_mtime_ns for p in out.rglob("*.npy")}
    again = run_batch(recs, options, client=client)
    assert again.tasks == 0 and not again.failed
    assert all(j.skipped for j in again.jobs)
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*.npy")} == stamps
    # an interrupted run: one chunk's outputs and marker missing, the recording not done
    book = out / "rec1" / ".batch"
    (book / "done.json").unlink()
    next(book.glob("chunk-00000006-*.json")).unlink()
    for stem in ("000006", "000007", "000008"):
        (out / "rec1" / f"{stem}.npy").unlink()
    resumed = run_batch(recs, options, client=client)
    assert resumed.tasks == 1  # that chunk only: no scan, no state pass
    assert_depths_equal(out / "rec1", expected["rec1"])


def test_cli_on_a_running_scheduler_equals_lightflow_replay(recordings, client, tmp_path, capsys):
    """Default pipeline options, chunks of 5 frames: the states before frames 5 and 10 come
    from the early frames whose blur refits fill the pool."""
    out, replayed = tmp_path / "out", tmp_path / "replayed"
    status = main(["batch", str(recordings[3]), "--out", str(out), "--chunk-frames", "5",
                   "--scheduler", client.scheduler.address])  # fmt: skip
    stdout, err = capsys.readouterr()
    assert status == 0, err
    assert "local Dask cluster" not in err
    # scan, state pass, 3 chunks
    assert f"1 of 1 recordings complete, {FRAMES + 3} frames, 5 tasks run" in stdout
    assert main(["replay", str(recordings[3]), "--export-depth", str(replayed)]) == 0
    capsys.readouterr()
    expected = {p.stem: np.load(p) for p in replayed.glob("*.npy") if not p.stem.endswith("_std")}
    assert len(expected) == FRAMES + 3
    assert_depths_equal(out / "rec3", expected)


def kill_worker_once(rec: str, indices: list[int]) -> None:
    """On the first chunk task that sees it, kill this worker process (like an OOM kill)."""
    marker = Path(rec).parent / "killed-once"
    if indices[0] == 3 and Path(rec).name == "rec2":
        try:
            fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            return
        os.close(fd)
        os._exit(1)


def test_a_killed_worker_is_retried(recordings, expected, client, tmp_path):
    out = tmp_path / "out"
    options = BatchOptions(out, config=CONFIG, chunk_frames=3, hook=kill_worker_once)
    report = run_batch([str(recordings[2])], options, client=client)
    assert (recordings[2].parent / "killed-once").exists()
    assert not report.failed
    assert_depths_equal(out / "rec2", expected["rec2"])
    client.wait_for_workers(2, timeout=60)  # the nanny restarted it


def test_nothing_listens_beyond_loopback(client):
    pids = {os.getpid()} | {p.pid for p in psutil.Process().children(recursive=True)}
    listening = [c.laddr for c in psutil.net_connections("inet")
                 if c.status == psutil.CONN_LISTEN and c.pid in pids]  # fmt: skip
    assert listening  # the scheduler, the workers and their nannies
    assert {a.ip for a in listening} == {"127.0.0.1"}


def test_cli_corrupt_recording_one_line_others_complete(recordings, tmp_path, capsys):
    good = replicate_recording(recordings[0], tmp_path / "good", 4)
    damaged = replicate_recording(recordings[0], tmp_path / "damaged", 4)
    (damaged / "frames" / "000002.png").unlink()
    garbage = shutil.copytree(good, tmp_path / "garbage")
    (garbage / "recording.json").write_text("{not json")
    blank = replicate_recording(recordings[0], tmp_path / "blank", 3)
    for png in (blank / "frames").iterdir():
        png.unlink()
        png.write_bytes(b"not a png")
    out = tmp_path / "out"
    argv = ["batch", str(good), str(damaged), str(garbage), str(blank), "--out", str(out),
            "--workers", "2"]  # fmt: skip
    status = main(argv)
    stdout, err = capsys.readouterr()
    assert status == 2, err
    assert "Traceback" not in err
    info = json.loads((out / "batch.json").read_text())["recordings"]
    assert info["good"]["status"] == info["damaged"]["status"] == "complete"
    assert sorted(p.name for p in (out / "good").glob("*.npy") if "_std" not in p.name) == [
        f"{i:06d}.npy" for i in range(4)
    ]
    assert sorted(p.name for p in (out / "damaged").glob("*.npy") if "_std" not in p.name) == [
        "000000.npy", "000001.npy", "000003.npy"
    ]
    assert info["damaged"]["frames_done"] == 3
    assert len(info["damaged"]["bad_frames"]) == 1
    line = info["damaged"]["bad_frames"][0]
    assert "000002.png: frame file missing (listed as frames[2])" in line
    for name, what in (("garbage", "recording.json"), ("blank", "none of the 3 frames")):
        e = info[name]
        assert e["status"] == "failed" and what in e["error"] and "\n" not in e["error"]
        assert f"lightflow: error: {e['error']}" in err
    assert "2 of 4 recordings complete" in stdout
    # the same command again: the complete ones are skipped, the failed ones tried again
    assert main(argv) == 2
    stdout, _ = capsys.readouterr()
    assert stdout.count("skipped") == 2




def test_a_chunk_starts_from_the_frame_ahead_of_it(tmp_path):
    """Lines that moved since the frame before count as moving
    (:func:`lightflow.app.core.flow.moved_lines`): a chunk processes the good frame ahead
    of it first (not written), seeded with the state before that frame, and equals a
    sequential replay.  Two balls at 5 ms on an 800x600 rig, whose third frame reads
    differently after another frame than the second (checked here, so that the test
    would see a chunk that skipped it)."""
    from lightflow.app.batch import chunk_task, state_task

    rig = load_rig(RIG_FILE).scaled(0.5)
    rec = tmp_path / "rec"
    cam = SyntheticCamera(rig, "two-balls", frames=3, exposure_s=0.005, fps=10,
                          sensor=SensorModel(samples=8))  # fmt: skip
    with cam, RecordingWriter(rec, rig, cam.exposure_s) as writer:
        for frame in cam.frames():
            assert writer.write(frame)
    config = PipelineConfig(stride=4)
    expected = sequential_depths(rec, config)
    # the third frame needs the second
    camera = RecordedCamera(rec)
    pipeline = DepthPipeline(camera.rig, config)
    with camera:
        frames = list(camera.frames())
    pipeline.process(frames[0])
    alone = pipeline.process(frames[2]).depth
    assert not np.array_equal(np.isnan(alone), np.isnan(expected[frames[2].stem]))
    # a chunk of the third frame alone
    states = state_task(str(rec), None, config, [0, 1, 2], [1])["states"]
    out = tmp_path / "out"
    chunk_task(str(rec), None, config, [2], 2, states[0], 1, str(out), True, False,
               str(tmp_path / "marker.json"))  # fmt: skip
    assert sorted(p.name for p in out.glob("*.npy")) == [f"{frames[2].stem}.npy",
                                                       f"{frames[2].stem}_std.npy"]
    np.testing.assert_array_equal(np.load(out / f"{frames[2].stem}.npy"),
                                  expected[frames[2].stem])
