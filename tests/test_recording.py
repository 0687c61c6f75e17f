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
from lightflow.app.errors import ConfigError, DriverError, FrameError
from lightflow.app.recording import (
    INDEX_LOG,
    RecordingWriter,
    benchmark_recorder,
    load_frame,
    read_recording,
)
from lightflow.app.rig import load_rig
from lightflow.drivers.base import Frame
from lightflow.drivers.replay import RecordedCamera

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
        "(expected only: bits, exposure_s, format, frames, rig)"
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
    (lambda d: d["frames"][0].update(file="../x.png"), "frames[0].file: expected a path inside"),
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
from lightflow.app.rig import load_rig
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


def test_recording_survives_kill_9(tmp_path, capsys):
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
    # every frame under its final name is complete; recording.json may lag behind
    on_disk = sorted(f"frames/{p.name}" for p in (root / "frames").glob("*.png"))
    assert set(e.file for e in rec.frames) <= set(on_disk)
    # verify names the unclosed recording (and any unlisted frames), then --repair relists
    assert cli_main(["verify", str(root)]) == 2
    assert "the recording was not closed" in capsys.readouterr().out
    assert cli_main(["verify", "--repair", str(root)]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[-1].endswith(f"{len(on_disk)} frames, 80x60, exposure 10 ms: OK")
    rec = read_recording(root)
    assert [e.file for e in rec.frames] == on_disk  # nothing written to disk is lost
    assert [e.t for e in rec.frames] == pytest.approx([0.01 * i for i in range(len(on_disk))])
    assert not list(root.rglob("*.tmp")) and not (root / INDEX_LOG).exists()
    for i in range(len(rec.frames)):
        assert load_frame(rec, i).shape == (H, W, 3)


def test_repair_removes_partial_files_and_keeps_listed(tmp_path, rig, capsys):
    root = tmp_path / "rec"
    write_recording(root, rig, n=3)
    # what a crash in the middle of frame 3 and of a recording.json rewrite leaves
    good = (root / "frames/000002.png").read_bytes()
    (root / "frames/.000003.png.tmp").write_bytes(good[:100])
    (root / ".recording.json.tmp").write_text('{"format": ')
    (root / "frames/000004.png").write_bytes(good[: len(good) // 2])  # cut PNG, not logged
    (root / INDEX_LOG).write_text(
        '{"file": "frames/000003.png", "t": 11.0}\n{"file": "frames/0000'
    )
    assert cli_main(["verify", str(root)]) == 2
    lines = capsys.readouterr().out.splitlines()
    assert lines[:-1] == [
        f"PROBLEM {root / INDEX_LOG}: the recording was not closed (crash or kill?); "
        f"1 more frame written: run `lightflow verify --repair {root}`",
        f"PROBLEM {root}/.recording.json.tmp: partial file left by an interrupted write "
        "(--repair removes it)",
        f"PROBLEM {root}/frames/.000003.png.tmp: partial file left by an interrupted write "
        "(--repair removes it)",
        f"PROBLEM {root}/frames/000004.png: not listed in recording.json",
    ]
    assert cli_main(["verify", "--repair", str(root)]) == 0
    out = capsys.readouterr().out
    assert f"repaired {root}/frames/000004.png: removed (incomplete PNG)" in out
    assert out.splitlines()[-1] == f"{root}: 3 frames, 80x60, exposure 20 ms: OK"
    assert sorted(p.name for p in root.iterdir()) == ["frames", "recording.json"]
    assert sorted(p.name for p in (root / "frames").iterdir()) == [
        "000000.png", "000001.png", "000002.png"
    ]


def test_bits_round_trip(tmp_path, rig):
    root = tmp_path / "rec"
    img = (make_image(0, np.uint16) >> 4).astype(np.uint16)  # 12-bit samples, unscaled
    with RecordingWriter(root, rig, 0.02) as writer:
        writer.write(Frame(0, 0.0, 0.02, img, bits=12) if _frame_has_bits() else
                     Frame(0, 0.0, 0.02, img))
        if not _frame_has_bits():
            writer.bits = 12
    rec = read_recording(root)
    assert rec.bits == 12
    assert json.loads((root / "recording.json").read_text())["bits"] == 12
    np.testing.assert_array_equal(load_frame(rec, 0), img)
    # a sample above 2**bits - 1 is off-contract
    edit_json(root, lambda d: d.update(bits=10))
    with pytest.raises(FrameError, match="more than bits = 10 allow"):
        load_frame(read_recording(root), 0)
    edit_json(root, lambda d: d.update(bits=17))
    with pytest.raises(ConfigError, match="bits: expected an integer 1..16"):
        read_recording(root)


def _frame_has_bits() -> bool:
    import dataclasses

    return "bits" in {f.name for f in dataclasses.fields(Frame)}


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda d: d["frames"][1].update(file="frames/./000001.png"), "frames[1].file: expected a path inside the recording folder, normalised"),  # noqa: E501
        (lambda d: d["frames"][1].update(file="frames//000001.png"), "frames[1].file: expected a path inside the recording folder, normalised"),  # noqa: E501
        (lambda d: d["frames"][1].update(file="frames/000000.png"), "frames[1].file: frames/000000.png is already frames[0]"),  # noqa: E501
        (lambda d: d["frames"][1].update(file="frames/" + "x" * 5000 + ".png"), "frames[1].file: expected a path of at most 255 characters (5011 given)"),  # noqa: E501
        (lambda d: d["frames"][1].update(file="frames/000001.jpg"), "frames[1].file: expected a .png file"),  # noqa: E501
        (lambda d: d["rig"]["camera"].update(width=10**12), "rig: camera.width: expected at most 16384 px"),  # noqa: E501
        (lambda d: d["rig"]["camera"]["K"][0].__setitem__(0, "1800"), "rig: camera.K: expected a 3x3 matrix of numbers"),  # noqa: E501
        (lambda d: d["rig"]["camera"].update(dist=[1e6, 0, 0, 0, 0]), "rig: camera.dist: coefficients move image points"),  # noqa: E501
        (lambda d: d.update(exposure_s=10**400), "exposure_s: expected a positive number of seconds, got an integer of 401 digits"),  # noqa: E501
    ],
)  # fmt: skip
def test_frame_paths_and_values_rejected(rec_dir, change, message):
    edit_json(rec_dir, change)
    with pytest.raises(ConfigError) as err:
        read_recording(rec_dir)
    assert str(err.value).startswith(f"{rec_dir}/recording.json: {message}")
    assert "\n" not in str(err.value)


def test_frame_symlinked_out_of_the_folder(rec_dir, tmp_path):
    outside = tmp_path / "outside.png"
    (rec_dir / "frames/000001.png").rename(outside)
    (rec_dir / "frames/000001.png").symlink_to(outside)
    with pytest.raises(FrameError, match=f"links to {outside}, outside the recording folder"):
        load_frame(read_recording(rec_dir), 1)


def test_jpeg_renamed_png(rec_dir):
    ok, buf = cv2.imencode(".jpg", make_image(1))
    (rec_dir / "frames/000001.png").write_bytes(buf.tobytes())
    with pytest.raises(FrameError, match="000001.png: not a PNG file"):
        load_frame(read_recording(rec_dir), 1)


def test_verify_flags_empty_recording(tmp_path, rig, capsys):
    RecordingWriter(tmp_path / "rec", rig, 0.02).close()
    assert cli_main(["verify", str(tmp_path / "rec"), "--rig", "two-projector"]) == 2
    out = capsys.readouterr().out
    assert "recording.json: frames: lists no frames (nothing to replay)" in out


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
        f"PROBLEM {rec_dir}/frames/000003.png: not a PNG file "
        "(a recording's frames are PNG images)",
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
    from lightflow.app.rig import save_rig

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
