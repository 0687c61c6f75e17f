"""End to end: simulate a small session of a known rig, calibrate it, compare."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from lightflow.app.cli import main
from lightflow.app.core.rig import ProjectorModel, Rig, load_rig, save_rig
from lightflow.calibration.gamma import measure_response
from lightflow.calibration.pipeline import calibrate_session
from lightflow.calibration.report import compare_rigs, placement_advice
from lightflow.calibration.session import read_session
from lightflow.calibration.simulate import (
    TRUTH_FILE,
    SimParams,
    scaled_rig,
    simulate_grey_ramp,
    simulate_session,
)

RIGS = "app/rigs"


@pytest.fixture(scope="module")
def small_rig():
    # camera 640x480, projectors 640x400
    return scaled_rig(load_rig(f"{RIGS}/two-projector.json"), 0.4, 0.5)


@pytest.fixture(scope="module")
def session_dir(small_rig, tmp_path_factory):
    out = tmp_path_factory.mktemp("cal")
    calls = []
    simulate_session(small_rig, 8, out, seed=3, progress=lambda i, n: calls.append((i, n)))
    assert calls[-1] == (8 * 2 * 40, 8 * 2 * 40)
    return out


@pytest.fixture(scope="module")
def calibrated(session_dir):
    return calibrate_session(session_dir)


def test_simulated_session_is_valid(session_dir, small_rig):
    s = read_session(session_dir)
    assert s.camera_size == (640, 480)
    assert [(p.name, p.width, p.height) for p in s.projectors] == [
        ("left", 640, 400), ("right", 640, 400)]
    assert s.projectors[0].patterns == small_rig.projectors[0].patterns
    truth = json.loads((session_dir / TRUTH_FILE).read_text())
    assert len(truth["board_poses"]) == 8


def test_calibration_close_to_truth(calibrated, small_rig):
    rig, report = calibrated
    cmp = compare_rigs(rig, small_rig)
    w = cmp["worst"]
    # bars at 1600x1200 are 0.5 %, 3 px, 3 mm, 0.2 deg; this session has 6x fewer pixels
    assert w["focal_pct"] < 0.6
    assert w["principal_px"] < 5.0
    assert w["position_mm"] < 4.0
    assert w["rotation_deg"] < 0.3
    assert report.rms < 0.2
    assert len(report.camera.per_view) == 8
    assert all(len(p.per_view) == 8 for p in report.projectors)
    assert [p.patterns for p in rig.projectors] == [p.patterns for p in small_rig.projectors]
    # camera-to-projector convention: X_proj = R @ X_cam + t
    for est, true in zip(rig.projectors, small_rig.projectors, strict=True):
        assert np.allclose(est.centre_in_camera, true.centre_in_camera, atol=4e-3)
    assert not report.warnings  # 8 varied poses


def test_cli_prints_report_and_writes_rig(session_dir, small_rig, tmp_path, capsys):
    out = tmp_path / "rig.json"
    assert main(["calibrate", str(session_dir), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "camera: RMS reprojection error" in text
    assert "against ground truth:" in text and "worst: focal" in text
    assert "projector gamma: not measured (the session has no gamma/ folder)" in text
    rig = load_rig(out)
    assert compare_rigs(rig, small_rig)["worst"]["position_mm"] < 4.0


def test_cli_error_on_missing_session(tmp_path, capsys):
    assert main(["calibrate", str(tmp_path), "--out", str(tmp_path / "r.json")]) == 2
    assert "session.json: file not found" in capsys.readouterr().err


def test_compare_rigs_reports_rotation_and_position(small_rig):
    assert compare_rigs(small_rig, small_rig)["pass"]
    p = small_rig.projectors[0]
    a = math.radians(0.5)
    Rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    moved = ProjectorModel(p.name, p.width, p.height, p.K, p.dist, Rz @ p.R,
                           p.t + [0.002, 0, 0], p.patterns)
    cmp = compare_rigs(Rig(small_rig.camera, (moved, small_rig.projectors[1])), small_rig)
    assert cmp["projectors"]["left"]["rotation_deg"] == pytest.approx(0.5)
    # the example rig stores R to 12 digits: a few 1e-5 degrees of rounding
    assert cmp["projectors"]["right"]["rotation_deg"] == pytest.approx(0.0, abs=1e-3)
    assert not cmp["pass"]


def test_placement_advice(small_rig):
    assert placement_advice(small_rig) == []
    left, right = small_rig.projectors
    # both projectors beside the camera at the same depth, pointing straight ahead
    par = [ProjectorModel(p.name, p.width, p.height, p.K, p.dist, np.eye(3),
                          np.array([-x, 0.0, 0.0]), p.patterns)
           for p, x in ((left, -0.3), (right, 0.35))]
    advice = placement_advice(Rig(small_rig.camera, tuple(par)))
    assert len(advice) == 2
    assert "move projector 'right' (on the camera's right)" in advice[1]
    assert "towards the scene" in advice[1]


def test_gamma_from_simulated_grey_ramp(small_rig):
    levels = [0, 32, 64, 96, 128, 160, 192, 224, 255]
    imgs = list(simulate_grey_ramp(small_rig, "right", levels, params=SimParams(gamma=2.2)))
    r = measure_response(imgs, levels)
    assert r.gamma == pytest.approx(2.2, abs=0.03)
    assert r.rms < 0.005
    assert r.inverse[0] == 0 and r.inverse[255] == 255
    assert abs(int(r.inverse[128]) - 255 * (128 / 255) ** (1 / 2.2)) <= 2


def test_cli_simulated_gamma_is_measured_by_calibrate(tmp_path, capsys):
    """simulate --calibration renders grey ramps; calibrate fits and reports the gamma."""
    rig_file = tmp_path / "small-rig.json"  # camera 400x300, projectors 320x200
    save_rig(scaled_rig(load_rig(f"{RIGS}/two-projector.json"), 0.25, 0.25), rig_file)
    cal = tmp_path / "cal"
    assert main(["simulate", "--calibration", "--rig", str(rig_file), "--poses", "4",
                 "--gamma", "1.8", "--out", str(cal)]) == 0
    assert "grey ramps (gamma 1.8)" in capsys.readouterr().out
    ramp = json.loads((cal / "gamma" / "ramp.json").read_text())
    assert ramp["levels"][:2] == [0, 255] and len(ramp["levels"]) == 10
    assert ramp["projectors"]["right"][2] == "gamma/right/002.png"
    for name in ("left", "right"):
        assert len(list((cal / "gamma" / name).glob("*.png"))) == 10
    # session.json stays exactly per formats.md: the ramp is an extra beside it
    assert "gamma" not in json.loads((cal / "session.json").read_text())
    assert read_session(cal).camera_size == (400, 300)

    assert main(["calibrate", str(cal), "--out", str(tmp_path / "rig.json")]) == 0
    text = capsys.readouterr().out
    found = dict(re.findall(r"^projector (\w+): gamma ([0-9.]+) ", text, re.M))
    assert set(found) == {"left", "right"}
    for value in found.values():
        assert float(value) == pytest.approx(1.8, abs=0.05)
    assert "note: projector left is not linear" in text
    assert "warning: only 4 good poses" in text
