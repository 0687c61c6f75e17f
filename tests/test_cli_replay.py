"""``lightflow replay`` end to end on a small synthetic recording, and its bad-input paths."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from rerun.chunk import RrdReader

from lightflow.app.cli import main
from lightflow.app.core.pipeline import PipelineConfig
from lightflow.app.core.rig import load_rig
from lightflow.app.recording import RecordingWriter, read_recording
from lightflow.drivers.sim.synthetic import SensorModel, SyntheticCamera

RIG_FILE = Path(__file__).resolve().parents[1] / "app" / "rigs" / "two-projector.json"
N_FRAMES = 3


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    rig = load_rig(RIG_FILE).scaled(0.25)
    root = tmp_path_factory.mktemp("rec") / "rec"
    cam = SyntheticCamera(rig, "board", frames=N_FRAMES, sensor=SensorModel(samples=8))
    with cam, RecordingWriter(root, rig, cam.exposure_s) as writer:
        for frame in cam.frames():
            assert writer.write(frame)
    return root


def copy_recording(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def test_replay_exports_depth_and_rrd(recording, tmp_path, capsys):
    depth_dir, rrd = tmp_path / "depth", tmp_path / "out" / "rec.rrd"
    status = main(["replay", str(recording), "--export-depth", str(depth_dir),
                   "--rrd", str(rrd), "--compress"])  # fmt: skip
    out, err = capsys.readouterr()
    assert status == 0, err
    names = sorted(p.name for p in depth_dir.iterdir())
    assert names == sorted([f"{i:06d}.npy" for i in range(N_FRAMES)]
                           + [f"{i:06d}_std.npy" for i in range(N_FRAMES)])  # fmt: skip
    files = [n for n in names if not n.endswith("_std.npy")]
    for f in files:
        depth = np.load(depth_dir / f)
        std = np.load(depth_dir / f.replace(".npy", "_std.npy"))
        assert depth.shape == (300, 400) and depth.dtype == np.float32
        assert std.shape == depth.shape and std.dtype == np.float32
        # a predicted error exactly where there is a depth, positive and below max_depth_std
        assert np.array_equal(np.isfinite(std), np.isfinite(depth))
        ok = np.isfinite(depth)
        limit = 1.02 * PipelineConfig().max_depth_std
        assert np.all(std[ok] > 0) and np.all(std[ok] <= limit * depth[ok])
    # the board is 0.6-0.9 m away: whatever got a depth must be near that
    depth = np.load(depth_dir / files[-1])
    finite = depth[np.isfinite(depth)]
    assert finite.size > 0 and 0.4 < float(np.median(finite)) < 1.1
    frames = set()
    for chunk in RrdReader(rrd).stream():
        if chunk.entity_path == "/world/camera/depth":
            rb = chunk.to_record_batch()
            frames.update(rb.column("frame").to_pylist())
    assert frames == set(range(N_FRAMES))
    assert f"processed {N_FRAMES} of {N_FRAMES} frames" in err
    # no blur in the rig and no wall: fitted, and the summary says how to measure it
    assert "lens blur (sigma " in err and "fitted on the moving bands" in err
    assert "`lightflow rig blur`" in err
    assert f"depth maps: {N_FRAMES} frames in {depth_dir}/" in out
    assert f"open with `rerun {rrd}`" in out


def test_replay_processes_good_frames_lists_bad_ones_exit_2(recording, tmp_path, capsys):
    rec = copy_recording(recording, tmp_path / "rec")
    (rec / "frames" / "000001.png").unlink()
    status = main(["replay", str(rec), "--export-depth", str(tmp_path / "d")])
    out, err = capsys.readouterr()
    assert status == 2, err
    assert "Traceback" not in err
    assert f"lightflow: error: 1 of {N_FRAMES} frames could not be replayed" in err
    assert sorted(p.name for p in (tmp_path / "d").glob("*.npy")
                  if not p.stem.endswith("_std")) == ["000000.npy", "000002.npy"]
    assert "bad frames 1" in err
    assert "000001.png: frame file missing (listed as frames[1])" in err


def test_replay_with_no_good_frame_exits_2(recording, tmp_path, capsys):
    rec = copy_recording(recording, tmp_path / "rec")
    for png in (rec / "frames").iterdir():
        png.write_bytes(b"not a png")
    status = main(["replay", str(rec)])
    _, err = capsys.readouterr()
    assert status == 2
    assert f"lightflow: error: {rec}: none of the {N_FRAMES} frames could be replayed" in err
    assert "Traceback" not in err
    assert len([ln for ln in err.splitlines() if "error" in ln]) == 1


def test_replay_unknown_key_is_one_line_exit_2(recording, tmp_path, capsys):
    rec = copy_recording(recording, tmp_path / "rec")
    doc = json.loads((rec / "recording.json").read_text())
    doc["gain"] = 3
    (rec / "recording.json").write_text(json.dumps(doc))
    status = main(["replay", str(rec), "--rrd", str(tmp_path / "x.rrd")])
    out, err = capsys.readouterr()
    assert status == 2
    lines = err.strip().splitlines()
    assert lines == [f"lightflow: error: {rec / 'recording.json'}: unknown key 'gain' "
                     "(expected only: exposure_s, format, frames, rig; "
                     "optional: bits)"]  # fmt: skip
    assert not (tmp_path / "x.rrd").exists()


def test_replay_rig_override_size_mismatch(recording, tmp_path, capsys):
    # the full-size rig does not fit the 400x300 frames: refused at once, exit 2
    status = main(["replay", str(recording), "--rig", str(RIG_FILE)])
    _, err = capsys.readouterr()
    assert status == 2
    assert err == (f"lightflow: error: --rig {RIG_FILE}: camera is 1600x1200, but the recording "
                   f"{recording} holds 400x300 frames\n")
    assert read_recording(recording).rig.camera.width == 400  # the recording is untouched


def test_replay_help_has_examples(capsys):
    with pytest.raises(SystemExit) as info:
        main(["replay", "--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    assert "lightflow replay rec/ --rrd out/rec.rrd" in out and "--export-depth DIR" in out


def _run_limited(args, env, fsize=None):
    import resource
    import signal
    import subprocess
    import sys

    def limit():
        if fsize is not None:
            # writes past the limit then fail with EFBIG instead of killing the process
            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
            resource.setrlimit(resource.RLIMIT_FSIZE, (fsize, fsize))

    return subprocess.run(
        [sys.executable, "-m", "lightflow.app.cli", *args],
        capture_output=True, text=True, env=env, preexec_fn=limit, timeout=900,
    )  # fmt: skip


@pytest.mark.parametrize("option", ["--export-depth", "--export-ply"])
def test_replay_full_disk_is_one_line_exit_2_and_no_partial_files(
    recording, tmp_path_factory, tmp_path, option
):
    """A real process under RLIMIT_FSIZE: every write of an export file fails mid-way."""
    import os

    cache = tmp_path_factory.getbasetemp() / "lut-cache-full-disk"
    env = {**os.environ, "LIGHTFLOW_CACHE": str(cache)}
    # build the LUT (and compile) without a limit: only the export must hit the full disk
    warm = _run_limited(["replay", str(recording)], env)
    assert warm.returncode == 0, warm.stderr
    out = tmp_path / "out"
    proc = _run_limited(["replay", str(recording), option, str(out)], env, fsize=16384)
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("lightflow: error:")]
    suffix = "npy" if option == "--export-depth" else "ply"
    assert len(errors) == 1
    # (the depth export writes 000000_std.npy, then 000000.npy)
    assert errors[0].startswith(f"lightflow: error: {out}/000000")
    assert f".{suffix}: cannot write: " in errors[0]
    # the OS says EFBIG, or Python's buffered writer reports the short write
    assert errors[0].endswith(("File too large", "written)")), errors[0]
    assert list(out.iterdir()) == []  # complete files only: no partial file, no .tmp


def test_replay_help_states_the_exit_codes_it_uses(capsys):
    with pytest.raises(SystemExit):
        main(["replay", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "Exit status: 0 when every frame was replayed; 2 when any frame was bad" in text
    assert "docs/formats.md" in text


def test_replay_with_a_bad_frame_exits_2_as_help_says(recording, tmp_path, capsys):
    rec = copy_recording(recording, tmp_path / "rec")
    (rec / "frames" / "000001.png").write_bytes(b"\x89PNG\r\n\x1a\n cut off")
    assert main(["replay", str(rec), "--export-depth", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err
    assert "1 of 3 frames could not be replayed" in err
    assert sorted(p.name for p in (tmp_path / "d").glob("*.npy")
                  if not p.stem.endswith("_std")) == ["000000.npy", "000002.npy"]


def test_summary_says_a_rig_blur_was_used():
    from lightflow.app.core.pipeline import DepthPipeline
    from lightflow.app.status import describe_blur

    rig = load_rig(RIG_FILE).scaled(0.25)
    line = describe_blur(DepthPipeline(rig.with_blur([(0.36, 0.36), (0.36, 0.36)])))
    assert line.startswith("lens blur") and "measured, from the rig file" in line
    assert "rig blur`" not in line


def test_the_summary_says_which_camera_response_was_used():
    from lightflow.app.core.pipeline import DepthPipeline, PipelineConfig
    from lightflow.app.core.rig import resolve_rig
    from lightflow.app.status import describe_response

    rig = resolve_rig("two-projector").scaled(0.25)
    line = describe_response(DepthPipeline(rig))
    assert "taken as linear (the rig file gives no camera.gamma)" in line
    assert "lightflow rig blur" in line
    pipe = DepthPipeline(rig, PipelineConfig(camera_gamma="auto"))
    assert "taken as linear (no lines stood still" in describe_response(pipe)
    line = describe_response(DepthPipeline(rig.with_camera_gamma(1.0)))
    assert line == "camera response: linear (from the rig file)"
    line = describe_response(DepthPipeline(rig, PipelineConfig(camera_gamma=2.2)))
    assert line == "camera response: gamma 2.2 (from --camera-gamma): frames linearised"


def test_the_summary_says_which_colour_crosstalk_was_used():
    from lightflow.app.core.pipeline import DepthPipeline, PipelineConfig
    from lightflow.app.core.rig import resolve_rig
    from lightflow.app.status import describe_crosstalk

    rig = resolve_rig("two-projector").scaled(0.25)
    line = describe_crosstalk(DepthPipeline(rig))
    assert line.startswith("colour crosstalk: not known") and "lightflow rig blur" in line
    line = describe_crosstalk(DepthPipeline(rig.with_crosstalk([0.04, 0.03])))
    assert line == ("colour crosstalk: the red channel sees 4.0 % of the blue light and the "
                    "blue channel sees 3.0 % of the red light (measured, from the rig file)")
    line = describe_crosstalk(DepthPipeline(rig, PipelineConfig(crosstalk=0.035)))
    assert line.endswith("(from the crosstalk option)") and "3.5 %" in line
