"""Strict reading of calibration session folders and the errors bad sessions give."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from lightflow.app.core.errors import CalibrationError, ConfigError, FrameError
from lightflow.calibration.graycode import frame_count
from lightflow.calibration.pipeline import calibrate_session
from lightflow.calibration.session import Board, read_session, write_session

PW, PH = 16, 8  # 4 column bits, 3 row bits: 16 frames
CAM = (64, 48)


def _make(tmp_path, poses=3, projectors=("left", "right"), size=CAM):
    """A structurally valid session of blank frames."""
    patterns = [{"channel": "red", "kind": "uniform", "pitch_px": 4.0, "width_px": 1.0,
                 "offset_px": 0.0},
                {"channel": "blue", "kind": "uniform", "pitch_px": 4.0, "width_px": 1.0,
                 "offset_px": 1.0}]
    n = frame_count(PW, PH)
    img = np.full((size[1], size[0]), 128, np.uint8)
    data = {
        "format": "lightflow-calibration/1",
        "board": {"kind": "checkerboard", "inner_corners": [9, 6], "square_m": 0.03},
        "camera": {"width": CAM[0], "height": CAM[1]},
        "projectors": [{"name": name, "width": PW, "height": PH, "patterns": [patterns[i]]}
                       for i, name in enumerate(projectors)],
        "sequence": "graycode/1",
        "poses": [],
    }
    for p in range(poses):
        frames = {}
        for name in projectors:
            frames[name] = []
            for i in range(n):
                rel = f"pose{p:02d}/{name}/{i:03d}.png"
                (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(tmp_path / rel), img)
                frames[name].append(rel)
        data["poses"].append({"name": f"pose{p:02d}", "frames": frames})
    (tmp_path / "session.json").write_text(json.dumps(data))
    return data


def _rewrite(tmp_path, data):
    (tmp_path / "session.json").write_text(json.dumps(data))


def test_valid_session_round_trips(tmp_path):
    _make(tmp_path)
    s = read_session(tmp_path)
    assert s.board == Board(9, 6, 0.03)
    assert s.camera_size == CAM
    assert [p.name for p in s.projectors] == ["left", "right"]
    assert len(s.poses) == 3 and len(s.poses[0].frames["left"]) == 16
    out = tmp_path / "copy"
    write_session(s, out)
    assert json.loads((out / "session.json").read_text()) == s.to_dict()


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda d: d.update(extra=1), "session: unknown key 'extra'"),
        (lambda d: d.update(sequence="graycode/2"), "sequence: expected 'graycode/1'"),
        (lambda d: d.update(format="x"), "format: expected 'lightflow-calibration/1'"),
        (lambda d: d["board"].update(inner_corners=[9]), "board.inner_corners"),
        (lambda d: d["board"].update(kind="circles"), "board.kind"),
        (lambda d: d["camera"].update(depth=8), "camera: unknown key 'depth'"),
        (lambda d: d["projectors"][1].update(K=[]), "projectors[1]: unknown key 'K'"),
        (lambda d: d["projectors"][0]["patterns"][0].update(channel="cyan"),
         "projectors[0].patterns[0].channel"),
        (lambda d: d["poses"][1]["frames"]["right"].pop(),
         "poses[1] (pose01).frames.right: expected 16 frames (graycode/1 for a 16x8 "
         "projector), got 15"),
        (lambda d: d["poses"][0]["frames"].pop("left"),
         "poses[0] (pose00).frames: missing frames of projector 'left'"),
        (lambda d: d["poses"][0]["frames"].update(middle=[]), "unknown projector 'middle'"),
        (lambda d: d["poses"][2].update(name="pose00"), "poses[2].name: expected a unique"),
        (lambda d: d["poses"][0]["frames"]["left"].__setitem__(0, "../x.png"),
         "expected a path inside the session folder"),
    ],
)
def test_bad_session_json_names_the_field(tmp_path, mutate, message):
    data = _make(tmp_path)
    mutate(data)
    _rewrite(tmp_path, data)
    with pytest.raises(ConfigError) as exc:
        read_session(tmp_path)
    assert message in str(exc.value)
    assert "session.json" in str(exc.value)


def test_missing_frame_names_pose_projector_frame(tmp_path):
    _make(tmp_path)
    (tmp_path / "pose01" / "right" / "005.png").unlink()
    with pytest.raises(FrameError) as exc:
        read_session(tmp_path)
    msg = str(exc.value)
    assert "pose pose01, projector right, frame 5 (column bit 2 inverse): file not found" in msg


def test_wrong_image_size_names_pose_projector_frame(tmp_path):
    _make(tmp_path)
    cv2.imwrite(str(tmp_path / "pose00" / "left" / "003.png"), np.zeros((24, 32), np.uint8))
    s = read_session(tmp_path)
    with pytest.raises(FrameError) as exc:
        list(s.iter_frames(s.poses[0], s.projectors[0]))
    msg = str(exc.value)
    assert "pose pose00, projector left, frame 3 (column bit 3 inverse)" in msg
    assert "image is 32x24, session.json camera is 64x48" in msg


def test_board_not_found_is_a_calibration_error(tmp_path):
    _make(tmp_path)
    with pytest.raises(CalibrationError) as exc:
        calibrate_session(tmp_path)
    msg = str(exc.value)
    assert "board found in 0 poses, need at least 3" in msg
    assert "pose pose02: board (9x6 inner corners) not found in the all-white frame" in msg


def test_missing_session_file(tmp_path):
    with pytest.raises(ConfigError, match="session.json: file not found"):
        read_session(tmp_path)


def test_board_option_parsing():
    assert Board.parse("9x6@0.030") == Board(9, 6, 0.03)
    with pytest.raises(ConfigError, match="--board"):
        Board.parse("9by6")
