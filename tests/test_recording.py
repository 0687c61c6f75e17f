"""Recordings: writer -> reader round trip, strict errors, crash safety, replay, verify."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from lightflow.app.cli import main as cli_main
from lightflow.app.core.errors import ConfigError, DriverError, FrameError
from lightflow.app.core.rig import load_rig
from lightflow.app.recording import (
    RecordingWriter,
    benchmark_recorder,
    load_frame,
    read_recording,
)
from lightflow.app.replay_camera import RecordedCamera
from lightflow.drivers.base import Frame

RIG_FILE = Path(__file__).resolve().parents[1] / "app" / "rigs" / "two-projector.json"
W, H = 80, 60  # two-projector rig scaled by 0.05


@pytest.fixture(scope="module")
def rig():
    return load_rig(RIG_FILE).scaled(0.05)


def make_image(i: int, dtype=np.uint8) -> np.ndarray:
    rng = np.random.default_rng(i)
    top = 255 if dtype == np.uint8 else 65535
    return rng.integers(0, top, (H, W, 3), endpoint=True).astype(dtype)


def write_recording(root: Path, rig, n: int = 4, dtype=np.uint8, exposure: float = 0.02):
    images = [make_image(i, dtype) for i in range(n)]
    with RecordingWriter(root, rig, exposure) as writer:
        for i, img in enumerate(images):
            assert writer.write(Frame(i, 10.0 + i / 30, exposure, img))
    assert writer.written == n and writer.dropped == 0
    return images


def edit_json(root: Path, change) -> None:
    path = root / "recording.json"
    doc = json.loads(path.read_text())
    change(doc)
    path.write_text(json.dumps(doc))


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_round_trip(tmp_path, rig, dtype):
    images = write_recording(tmp_path / "rec", rig, dtype=dtype)
    rec = read_recording(tmp_path / "rec")
    assert rec.exposure_s == 0.02
    assert [e.file for e in rec.frames] == [f"frames/{i:06d}.png" for i in range(4)]
    assert [e.t for e in rec.frames] == pytest.approx([10.0 + i / 30 for i in range(4)])
    assert rec.rig.to_dict() == rig.to_dict()
    for i, img in enumerate(images):
        got = load_frame(rec, i)
        assert got.dtype == dtype
        np.testing.assert_array_equal(got, img)  # lossless and RGB (not BGR)
    # the PNG on disk is BGR as OpenCV writes it: channel 0 of the file is blue
    raw = cv2.imread(str(tmp_path / "rec/frames/000000.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(raw[..., 0], images[0][..., 2])


def test_writer_refuses_existing_recording(tmp_path, rig):
    write_recording(tmp_path / "rec", rig, n=1)
    with pytest.raises(ConfigError, match="already holds a recording"):
        RecordingWriter(tmp_path / "rec", rig, 0.02)


def test_writer_extra_hook_and_empty_recording(tmp_path, rig):
    def extra(root: Path, frame: Frame) -> None:
        (root / "truth").mkdir(exist_ok=True)
        np.save(root / "truth" / f"{frame.stem}.npy", frame.extras["truth"])

    writer = RecordingWriter(tmp_path / "rec", rig, 0.01, extra=extra)
    assert read_recording(tmp_path / "rec").frames == ()  # valid before the first frame
    writer.write(Frame(0, 0.0, 0.01, make_image(0), name="a", extras={"truth": np.arange(3)}))
    writer.close()
    writer.close()  # twice is fine
    assert np.load(tmp_path / "rec/truth/a.npy").tolist() == [0, 1, 2]
    assert read_recording(tmp_path / "rec").frames[0].file == "frames/a.png"


def test_writer_drops_after_timeout_and_counts(tmp_path, rig):
    gate = threading.Event()

    def slow_extra(root, frame):
        gate.wait()  # the disk "stalls" until released

    writer = RecordingWriter(tmp_path / "rec", rig, 0.01, queue_size=1, put_timeout_s=0.05,
                             extra=slow_extra)  # fmt: skip
    results = [writer.write(Frame(i, i * 0.1, 0.01, make_image(i))) for i in range(5)]
    gate.set()
    writer.close()
    # frame 0 is in the writer, frame 1 waits in the queue, the rest time out
    assert results == [True, True, False, False, False]
    assert writer.dropped == 3 and writer.written == 2
    assert len(read_recording(tmp_path / "rec").frames) == 2


def test_writer_thread_error_reaches_caller(tmp_path, rig):
    def broken(root, frame):
        raise FrameError("disk on fire")

    writer = RecordingWriter(tmp_path / "rec", rig, 0.01, extra=broken)
    writer.write(Frame(0, 0.0, 0.01, make_image(0)))
    with pytest.raises(FrameError, match="disk on fire"):
        writer.close()


# ----------------------------------------------------------------------------- strict reading


@pytest.fixture
def rec_dir(tmp_path, rig):
    write_recording(tmp_path / "rec", rig)
    return tmp_path / "rec"


def test_unknown_key(rec_dir):
    edit_json(rec_dir, lambda d: d.update(fps=30))
    with pytest.raises(ConfigError) as err:
        read_recording(rec_dir)
    assert str(err.value) == (
        f"{rec_dir}/recording.json: unknown key 'fps' "
        "(expected only: exposure_s, format, frames, rig; optional: bits)"
    )


def test_wrong_format(rec_dir):
    edit_json(rec_dir, lambda d: d.update(format="lightflow-recording/2"))
    with pytest.raises(ConfigError) as err:
        read_recording(rec_dir)
    assert str(err.value) == (
        f"{rec_dir}/recording.json: format: expected 'lightflow-recording/1', "
        'got "lightflow-recording/2"'
    )


def test_wrong_matrix_shape_in_rig(rec_dir):
    edit_json(rec_dir, lambda d: d["rig"]["camera"].update(K=[[1, 0, 0], [0, 1, 0]]))
    with pytest.raises(ConfigError) as err:
        read_recording(rec_dir)
    assert str(err.value) == (
        f"{rec_dir}/recording.json: rig: camera.K: expected a 3x3 matrix, got 2x3"
    )


SECONDS = "expected a number of seconds, got"
BAD_FIELDS = [
    (lambda d: d.update(exposure_s=0), "exposure_s: expected a positive number of seconds, got 0"),
    (lambda d: d.update(exposure_s="30ms"), f'exposure_s: {SECONDS} "30ms"'),
    (lambda d: d.pop("frames"), "missing key 'frames'"),
    (lambda d: d["frames"][1].update(t="x"), f'frames[1].t: {SECONDS} "x"'),
    (lambda d: d["frames"][2].update(size=3), "frames[2]: unknown key 'size'"),
    (lambda d: d["frames"][0].update(file="../x.png"), "frames[0].file: expected a plain path"),
]


@pytest.mark.parametrize(("change", "message"), BAD_FIELDS)
def test_bad_fields(rec_dir, change, message):
    edit_json(rec_dir, change)
    with pytest.raises(ConfigError) as err:
        read_recording(rec_dir)
    assert str(err.value).startswith(f"{rec_dir}/recording.json: {message}")


def test_not_json(rec_dir):
    (rec_dir / "recording.json").write_text("{")
    with pytest.raises(ConfigError, match=r"recording\.json: not valid JSON"):
        read_recording(rec_dir)


def test_missing_frame(rec_dir):
    (rec_dir / "frames/000002.png").unlink()
    rec = read_recording(rec_dir)
    with pytest.raises(FrameError) as err:
        load_frame(rec, 2)
    expected = f"{rec_dir}/frames/000002.png: frame file missing (listed as frames[2])"
    assert str(err.value) == expected


def test_unreadable_frame(rec_dir):
    (rec_dir / "frames/000001.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    with pytest.raises(FrameError) as err:
        load_frame(read_recording(rec_dir), 1)
    assert str(err.value) == f"{rec_dir}/frames/000001.png: not a readable image"


def test_grey_frame(rec_dir):
    cv2.imwrite(str(rec_dir / "frames/000001.png"), np.zeros((H, W), np.uint8))
    with pytest.raises(
        FrameError, match=r"000001\.png: expected an RGB image \(3 channels\), got 1"
    ):
        load_frame(read_recording(rec_dir), 1)


def test_frame_of_wrong_size(rec_dir):
    cv2.imwrite(str(rec_dir / "frames/000003.png"), np.zeros((30, 40, 3), np.uint8))
    with pytest.raises(FrameError) as err:
        load_frame(read_recording(rec_dir), 3)
    assert str(err.value) == (
        f"{rec_dir}/frames/000003.png: 40x30, expected 80x60 (camera.width x camera.height)"
    )


def test_rig_override_sets_expected_size(rec_dir, rig):
    big = load_rig(RIG_FILE).scaled(0.1)
    rec = read_recording(rec_dir, big)
    assert rec.rig is big
    with pytest.raises(FrameError, match="80x60, expected 160x120"):
        load_frame(rec, 0)


# ----------------------------------------------------------------------------- crash safety

CHILD = """
import sys, numpy as np
from lightflow.app.recording import RecordingWriter
from lightflow.app.core.rig import load_rig
from lightflow.drivers.base import Frame
rig = load_rig(sys.argv[2]).scaled(0.05)
w = RecordingWriter(sys.argv[1], rig, 0.01, put_timeout_s=10)
rng = np.random.default_rng(0)
i = 0
while True:
    w.write(Frame(i, i * 0.01, 0.01, rng.integers(0, 255, (60, 80, 3), dtype=np.uint8)))
    i += 1
    if w.written >= 20:
        print("written", flush=True)
"""


def test_recording_survives_kill_9(tmp_path):
    root = tmp_path / "rec"
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(root), str(RIG_FILE)],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout.readline().strip() == "written"  # killed while still writing
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        proc.stdout.close()
    rec = read_recording(root)
    assert len(rec.frames) >= 20
    for i in range(len(rec.frames)):
        assert load_frame(rec, i).shape == (H, W, 3)
    # frames whose file was complete but not yet listed are not lost: the index names
    # them, and --repair relists them and removes what was cut off mid-write
    indexed = [json.loads(line)["file"] for line in (root / "frames.index").read_text()
               .splitlines() if line.endswith("}")]  # fmt: skip
    assert cli_main(["verify", str(root), "--repair"]) == 0
    repaired = read_recording(root)
    assert [e.file for e in repaired.frames] == indexed
    assert len(repaired.frames) >= len(rec.frames)
    for i in range(len(repaired.frames)):
        assert load_frame(repaired, i).shape == (H, W, 3)
    on_disk = sorted(p.name for p in (root / "frames").iterdir())
    assert on_disk == sorted(Path(f).name for f in indexed)
    assert not list(root.glob(".*.tmp"))


def test_verify_reports_unlisted_and_temporary_files(rec_dir, capsys):
    (rec_dir / "frames" / "000009.png").write_bytes(b"\x89PNG\r\n\x1a\n cut off")
    (rec_dir / ".recording.json.tmp").write_text("{")
    assert cli_main(["verify", str(rec_dir)]) == 2
    out = capsys.readouterr().out
    assert "1 file(s) not listed in recording.json (first 000009.png" in out
    assert ".recording.json.tmp: leftover temporary file" in out
    assert cli_main(["verify", str(rec_dir), "--repair"]) == 0
    assert not (rec_dir / "frames" / "000009.png").exists()


def test_verify_flags_a_recording_without_frames(rec_dir, capsys):
    edit_json(rec_dir, lambda d: d.update(frames=[]))
    for p in (rec_dir / "frames").iterdir():
        p.unlink()
    assert cli_main(["verify", str(rec_dir)]) == 2
    assert "the recording lists no frame" in capsys.readouterr().out


@pytest.mark.parametrize("file, why", [
    ("frames/./000000.png", "expected a plain path inside the recording folder"),
    ("frames//000000.png", "expected a plain path inside the recording folder"),
    ("frames/000000.jpg", "expected a .png file"),
    ("frames/" + "x" * 5000 + ".png", "file name longer than 200 bytes"),
])  # fmt: skip
def test_frame_paths_are_plain_pngs(rec_dir, file, why):
    edit_json(rec_dir, lambda d: d["frames"][1].update(file=file))
    with pytest.raises(ConfigError, match=why):
        read_recording(rec_dir)


def test_frame_listed_twice_is_rejected(rec_dir):
    edit_json(rec_dir, lambda d: d["frames"][1].update(file=d["frames"][0]["file"]))
    with pytest.raises(ConfigError, match=r"frames\[1\].file: frames/000000.png is already "
                       r"frames\[0\]"):
        read_recording(rec_dir)


def test_frame_linked_outside_the_folder_is_rejected(rec_dir, tmp_path):
    outside = tmp_path / "outside.png"
    (rec_dir / "frames" / "000001.png").rename(outside)
    (rec_dir / "frames" / "000001.png").symlink_to(outside)
    with pytest.raises(FrameError, match="a link to a file outside the recording folder"):
        load_frame(read_recording(rec_dir), 1)


def test_jpeg_named_png_is_rejected(rec_dir):
    ok, jpeg = cv2.imencode(".jpg", make_image(1))
    (rec_dir / "frames" / "000001.png").write_bytes(jpeg.tobytes())
    with pytest.raises(FrameError, match="not a PNG file"):
        load_frame(read_recording(rec_dir), 1)


# ----------------------------------------------------------------------------- replay


def test_replay_skips_bad_frames_and_lists_them(rec_dir, rig):
    (rec_dir / "frames/000001.png").unlink()
    cv2.imwrite(str(rec_dir / "frames/000002.png"), np.zeros((30, 40, 3), np.uint8))
    cam = RecordedCamera(rec_dir)
    assert cam.uri == f"replay:{rec_dir}"
    assert cam.size == (W, H) and cam.exposure_s == 0.02
    with cam:
        frames = list(cam.frames())
    assert [(f.index, f.name) for f in frames] == [(0, "000000"), (3, "000003")]
    assert frames[1].timestamp == pytest.approx(10.1)
    np.testing.assert_array_equal(frames[1].image, make_image(3))
    assert cam.bad_frames == [
        f"{rec_dir}/frames/000001.png: frame file missing (listed as frames[1])",
        f"{rec_dir}/frames/000002.png: 40x30, expected 80x60 (camera.width x camera.height)",
    ]


def test_replay_exposure_is_fixed(rec_dir):
    cam = RecordedCamera(rec_dir)
    assert cam.set_exposure(0.02) == 0.02
    with pytest.raises(DriverError, match="exposure is fixed at 20 ms, cannot set 10 ms"):
        cam.set_exposure(0.01)


def test_replay_loop_and_stop(rec_dir):
    cam = RecordedCamera(rec_dir, loop=True)
    got = []
    with cam:
        for frame in cam.frames():
            got.append((frame.index, round(frame.timestamp, 6)))
            if len(got) == 6:
                cam.stop()
    lap = 4 / 30  # three frame periods plus one
    assert got[4] == (4, round(10.0 + lap, 6)) and len(got) == 6


def test_replay_realtime_pacing(tmp_path, rig):
    root = tmp_path / "rec"
    with RecordingWriter(root, rig, 0.01) as w:
        for i in range(4):
            w.write(Frame(i, i * 0.1, 0.01, make_image(i)))
    import time

    cam = RecordedCamera(root, realtime=True)
    start = time.perf_counter()
    with cam:
        stamps = [time.perf_counter() - start for _ in cam.frames()]
    assert stamps[-1] == pytest.approx(0.3, abs=0.08)
    assert stamps[0] < 0.08


# ----------------------------------------------------------------------------- verify


def test_verify_clean(rec_dir, capsys):
    assert cli_main(["verify", str(rec_dir)]) == 0
    out = capsys.readouterr().out
    assert out == f"{rec_dir}: 4 frames, 80x60, exposure 20 ms: OK\n"


def test_verify_lists_every_problem(rec_dir, capsys):
    (rec_dir / "frames/000001.png").unlink()
    (rec_dir / "frames/000003.png").write_bytes(b"nope")
    edit_json(rec_dir, lambda d: d["frames"][2].update(t=0.0))
    assert cli_main(["verify", str(rec_dir)]) == 2
    lines = capsys.readouterr().out.splitlines()
    assert lines == [
        f"PROBLEM {rec_dir}/recording.json: frames[2].t: 0 s does not increase "
        "(frames[1].t = 10.0333 s)",
        f"PROBLEM {rec_dir}/frames/000001.png: frame file missing (listed as frames[1])",
        f"PROBLEM {rec_dir}/frames/000003.png: not a PNG file (frames must be PNG)",
        f"{rec_dir}: 4 frames, 80x60, exposure 20 ms: 3 problems",
    ]


def test_verify_bad_json(rec_dir, capsys):
    edit_json(rec_dir, lambda d: d.update(format="x"))
    assert cli_main(["verify", str(rec_dir)]) == 2
    out = capsys.readouterr().out
    assert "recording.json: format: expected 'lightflow-recording/1'" in out


def test_verify_help(capsys):
    with pytest.raises(SystemExit):
        cli_main(["verify", "--help"])
    assert "Exit status: 0 when the recording" in capsys.readouterr().out


# ----------------------------------------------------------------------------- benchmark


def test_benchmark_recorder_small(tmp_path, capsys):
    result = benchmark_recorder(width=160, height=120, fps=50, seconds=0.4)
    assert result["offered"] == 20 and result["written"] + result["dropped"] == 20
    assert result["written"] == 20 and result["mib_per_s"] > 0
    assert capsys.readouterr() == ("", "")


def test_verify_with_rig_override(rec_dir, tmp_path, capsys):
    from lightflow.app.core.rig import save_rig

    save_rig(load_rig(RIG_FILE).scaled(0.1), tmp_path / "big.json")
    assert cli_main(["verify", str(rec_dir), "--rig", str(tmp_path / "big.json")]) == 2
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 5 and lines[-1].endswith("160x120, exposure 20 ms: 4 problems")
    assert lines[0].endswith("000000.png: 80x60, expected 160x120 (camera.width x camera.height)")


def test_replay_with_rig_override_checks_its_size(rec_dir):
    cam = RecordedCamera(rec_dir, rig=load_rig(RIG_FILE).scaled(0.1))
    assert cam.size == (160, 120)
    with cam:
        assert list(cam.frames()) == []
    assert len(cam.bad_frames) == 4


def test_twelve_bit_frames_record_and_replay_with_their_bits(tmp_path, rig):
    root = tmp_path / "rec12"
    image = (make_image(1).astype(np.uint16) * 16).astype(np.uint16)  # 0..4080
    with RecordingWriter(root, rig, 0.02) as w:
        w.write(Frame(0, 0.0, 0.02, image, bits=12))
    doc = json.loads((root / "recording.json").read_text())
    assert doc["bits"] == 12
    with RecordedCamera(root) as cam:
        (frame,) = list(cam.frames())
    assert frame.bits == 12 and frame.full_scale == 4095
    np.testing.assert_array_equal(frame.image, image)
