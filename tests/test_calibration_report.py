"""Report warnings from constructed inputs: outlier poses, too few poses, tilt variety, gamma."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lightflow.app.core.geometry import project_points
from lightflow.app.core.rig import load_rig
from lightflow.calibration.gamma import Response, gamma_lines
from lightflow.calibration.pipeline import GOOD_POSES, calibrate_camera, pose_warnings
from lightflow.calibration.report import DeviceReport, Report
from lightflow.calibration.simulate import DEFAULT_BOARD, generate_poses, scaled_rig


def _normal(about_vertical_deg: float, about_horizontal_deg: float) -> np.ndarray:
    n = np.array([math.tan(math.radians(about_vertical_deg)),
                  math.tan(math.radians(about_horizontal_deg)), 1.0])
    return n / np.linalg.norm(n)


VARIED = np.array([_normal(a, b) for a, b in
                   [(-20, 0), (20, 0), (0, -20), (0, 20), (15, 15), (-15, -15)]])


@pytest.fixture(scope="module")
def board_views():
    """Board corners of 7 poses seen by a 640x480 camera, pose03 badly detected."""
    rig = scaled_rig(load_rig("app/rigs/two-projector.json"), 0.4, 0.5)
    cam = rig.camera
    obj = DEFAULT_BOARD.object_points()
    rng = np.random.default_rng(1)
    corners = {}
    for i, (R, t) in enumerate(generate_poses(rig, DEFAULT_BOARD, 7, seed=2)):
        px = project_points(cam.K, cam.dist, obj.astype(float) @ R.T + t)
        px = px + rng.normal(0, 0.05, px.shape)
        if i == 3:  # corners found on a blurred, moving board
            px = px + rng.normal(0, 2.5, px.shape)
        corners[f"pose{i:02d}"] = px.astype(np.float32)
    return corners, obj, (cam.width, cam.height)


def test_outlier_pose_is_left_out_and_named(board_views):
    corners, obj, size = board_views
    skipped = {"pose07": "board (9x6 inner corners) not found in the all-white frame"}
    cam, used, rejected = calibrate_camera(corners, skipped, obj, size)
    assert used == [f"pose{i:02d}" for i in range(7) if i != 3]
    assert set(rejected) == {"pose03", "pose07"}
    assert "camera reprojection error over 3x the median" in rejected["pose03"]
    assert cam.rms < 0.2 and len(cam.per_view) == 6

    report = Report(DeviceReport("camera", cam.rms, dict(zip(used, cam.per_view, strict=True)),
                                 rejected), [], 8)
    lines = report.summary_lines()
    assert lines[0].startswith("camera: RMS reprojection error") and "over 6 of 8 poses" in lines[0]
    assert any(ln.startswith("  left out pose03: camera reprojection error") for ln in lines)
    assert any(ln.startswith("  left out pose07: board (9x6 inner corners) not found")
               for ln in lines)


def test_too_few_good_poses_warning():
    assert pose_warnings(GOOD_POSES, VARIED) == []
    warnings = pose_warnings(4, VARIED)
    assert warnings == ["only 4 good poses; use at least 6 for a reliable calibration"]
    report = Report(DeviceReport("camera", 0.1, {}), [], 4, warnings)
    assert "warning: only 4 good poses; use at least 6 for a reliable calibration" in \
        report.summary_lines()


def test_tilt_variety_warning():
    # turned left-right only: no tilt up-down
    flat = np.array([_normal(a, 0) for a in (-25, -10, 0, 10, 25, 5)])
    (w,) = pose_warnings(6, flat)
    assert w.startswith("poses lack tilt variety: the board turned over 50 deg left-right and "
                        "0 deg up-down")
    # all poses facing the camera
    facing = np.array([_normal(a, b) for a, b in [(1, 0), (0, 1), (-2, 2), (3, -1), (0, 0),
                                                  (2, 2)]])
    assert any("lack tilt variety" in w for w in pose_warnings(8, facing))
    # normals pointing away from the camera count the same as towards it
    assert pose_warnings(6, -VARIED) == []


def _response(gamma: float) -> Response:
    levels = np.array([0, 255, 64, 128, 192], float)
    return Response(gamma, levels, (levels / 255) ** gamma, 0.002, np.arange(256, dtype=np.uint8))


def test_gamma_lines():
    assert gamma_lines(None) == ["projector gamma: not measured (the session has no gamma/ "
                                 "folder)"]
    lines = gamma_lines({"left": _response(2.2), "right": _response(1.05),
                         "extra": "grey ramp: only 3 pixels brighten"})
    assert lines[0].startswith("projector left: gamma 2.20 ")
    assert "grey 128 gives 22 % of white" in lines[0]
    assert lines[1].startswith("  note: projector left is not linear") and "'raw'" in lines[1]
    assert lines[2].startswith("projector right: gamma 1.05 ")
    assert lines[3] == "projector extra: gamma not measured: grey ramp: only 3 pixels brighten"


def test_calibrate_help_and_rerun_options(tmp_path, capsys):
    from lightflow.app.cli import main

    with pytest.raises(SystemExit):
        main(["calibrate", "--help"])
    text = capsys.readouterr().out
    assert "``" not in text and "Examples:" in text
    assert "lightflow calibrate cal --out rig.json" in text and "--spawn" in text
    assert main(["calibrate", str(tmp_path), "--out", str(tmp_path / "rig.json"),
                 "--rrd", str(tmp_path / "p.rrd")]) == 2
    assert "--rrd and --spawn show a live capture" in capsys.readouterr().err
