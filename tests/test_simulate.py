"""``lightflow simulate``: recordings with ground truth, calibration sessions, option errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lightflow.app.cli import main as cli_main
from lightflow.app.core.errors import ConfigError
from lightflow.app.core.rig import resolve_rig
from lightflow.app.recording import load_frame, read_recording
from lightflow.calibration.session import read_session
from lightflow.drivers.sim.synthetic import GroundTruth

W, H = 400, 300  # example rigs scaled by 0.25


@pytest.fixture(scope="module")
def board_rec(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "board"
    status = cli_main(["simulate", "--scene", "board", "--scale", "0.25", "--frames", "2",
                       "--out", str(out)])  # fmt: skip
    assert status == 0
    return out


def test_recording_reads_back_with_ground_truth(board_rec):
    rec = read_recording(board_rec)
    assert (rec.rig.camera.width, rec.rig.camera.height) == (W, H)
    assert rec.exposure_s == pytest.approx(0.02)  # the board's nominal exposure
    assert [e.file for e in rec.frames] == ["frames/000000.png", "frames/000001.png"]
    assert rec.frames[1].t == pytest.approx(1 / 30)
    image = load_frame(rec, 1)
    assert image.shape == (H, W, 3) and image.dtype == np.uint8
    assert image.max() > 80  # lit lines (about 95 DN at their peak), not a black frame
    for stem in ("000000", "000001"):
        truth = GroundTruth.load(board_rec / "ground_truth" / f"{stem}.npz")
        assert truth.depth.shape == truth.object_id.shape == truth.lit.shape == (H, W)
        assert truth.planar
        on_board = truth.object_id >= 2
        assert on_board.mean() > 0.5
        assert 0.6 <= np.nanmin(truth.depth[on_board]) <= np.nanmax(truth.depth) <= 0.9
    scene = json.loads((board_rec / "ground_truth" / "scene.json").read_text())
    assert scene["scene"] == "board" and scene["planar"] is True
    assert scene["exposure_s"] == pytest.approx(0.02)
    assert scene["rig_digest"] == rec.rig.digest()


def test_sixteen_bit_frames_and_exposure(tmp_path, capsys):
    out = tmp_path / "ball16"
    assert cli_main(["simulate", "--scene", "ball", "--rig", "single-projector", "--scale",
                     "0.25", "--frames", "1", "--exposure", "0.004", "--bit-depth", "16",
                     "--out", str(out)]) == 0  # fmt: skip
    rec = read_recording(out)
    assert rec.exposure_s == pytest.approx(0.004)
    assert len(rec.rig.projectors) == 1
    assert load_frame(rec, 0).dtype == np.uint16
    assert "1 frames of 'ball'" in capsys.readouterr().out


def test_help_lists_scenes(capsys):
    with pytest.raises(SystemExit) as exc:
        cli_main(["simulate", "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    for name in ("board", "textured-board", "tilted-board", "ball", "fan", "two-balls"):
        assert f"  {name} " in text
    assert "a spinning fan in front of a static wall" in text


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--exposure", "0.05"], "longer than the frame period"),
        (["--frames", "0"], "--frames"),
        (["--rig", "no-such-rig"], "no-such-rig: file not found"),
        ([], "give --scene"),
    ],
)
def test_option_errors_are_one_line(tmp_path, capsys, extra, message):
    args = ["simulate", "--scale", "0.25", "--out", str(tmp_path / "r")]
    if extra != []:
        args += ["--scene", "board"]
    assert cli_main(args + extra) == 2
    err = capsys.readouterr().err
    assert err.startswith("lightflow: error: ") and err.count("\n") == 1
    assert message in err


def test_refuses_to_overwrite_a_recording(board_rec, capsys):
    args = ["simulate", "--scene", "board", "--scale", "0.25", "--frames", "1",
            "--out", str(board_rec)]  # fmt: skip
    assert cli_main(args) == 2
    assert "already holds a recording" in capsys.readouterr().err


def test_calibration_session(tmp_path):
    out = tmp_path / "cal"
    assert cli_main(["simulate", "--calibration", "--poses", "1", "--scale", "0.25",
                     "--out", str(out)]) == 0  # fmt: skip
    session = read_session(out)
    assert len(session.poses) == 1
    assert session.camera_size == (W, H)
    # graycode/1 for a 1280x800 projector: 2 + 2 * (11 + 10) frames
    assert [len(session.poses[0].frames[p.name]) for p in session.projectors] == [44, 44]
    assert (out / "ground_truth.json").is_file()


def test_resolve_rig_by_name_and_path(tmp_path):
    rig = resolve_rig("two-projector")
    assert (rig.camera.width, rig.camera.height) == (1600, 1200)
    assert len(resolve_rig("single-projector").projectors) == 1
    with pytest.raises(ConfigError, match="file not found"):
        resolve_rig(tmp_path / "missing.json")


def test_ball_wall_scene_has_a_static_wall_behind_a_moving_ball():
    from lightflow.drivers.sim.scenes import get_scene
    from lightflow.drivers.sim.synthetic import SceneRenderer

    rig = resolve_rig("two-projector").scaled(0.1)
    truth = SceneRenderer(rig, get_scene("ball-wall")).truth(0.05)
    wall = truth.object_id == 1
    ball = truth.object_id == 2
    assert wall.mean() > 0.5 and 0.01 < ball.mean() < 0.3
    assert np.allclose(truth.depth[wall], 1.1, atol=1e-4)  # the wall is the plane z = 1.1 m
    assert 0.5 < np.nanmax(truth.depth[ball]) < 1.0


def test_demo_no_save_without_a_viewer_is_one_line(monkeypatch, capsys):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert cli_main(["demo", "--no-save", "--frames", "1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lightflow: error: --no-save") and err.count("\n") == 1


def test_demo_streams_frames_into_an_rrd(tmp_path, capsys):
    # a small camera: the same steps as the default demo (tables, depth table,
    # renderer, pipeline warm-up with frames rendered ahead, streaming)
    out = tmp_path / "out"
    args = ["demo", "--frames", "3", "--scale", "0.2", "--no-viewer", "--out", str(out)]
    assert cli_main(args) == 0
    text = capsys.readouterr().out
    for step in ("[1/4]", "[2/4]", "[3/4]", "[4/4]", "first depth picture after"):
        assert step in text
    assert "Rerun: 3 frames" in text
    assert (out / "demo.rrd").stat().st_size > 0
