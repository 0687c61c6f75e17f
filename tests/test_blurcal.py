"""``lightflow rig blur``: the blur of each pattern measured on still lines at three depths.

The simulator blurs with a Gaussian lens of 0.6 px and a projector defocus of
0.6 projector px: sigma^2 = 0.36 + 0.36 m^2 (camera px, m = magnification).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from lightflow.app.blurcal import measure_blur, measure_crosstalk, measure_response
from lightflow.app.cli import main
from lightflow.app.core.flow import FlowModel, FlowParams
from lightflow.app.core.pipeline import DepthPipeline, PipelineConfig
from lightflow.app.core.rig import load_rig
from lightflow.app.recording import RecordingWriter, read_recording, recording_frames
from lightflow.drivers.sim.synthetic import SensorModel, SyntheticCamera

RIG_FILE = Path(__file__).resolve().parents[1] / "app" / "rigs" / "two-projector.json"


def truth_sigma(m: float) -> float:
    return math.sqrt(0.36 + 0.36 * m * m)


@pytest.fixture(scope="module")
def steps(tmp_path_factory) -> Path:
    """A board standing still at 0.55, 0.75 and 1.0 m, one frame each (half resolution)."""
    rig = load_rig(RIG_FILE).scaled(0.5)
    root = tmp_path_factory.mktemp("steps") / "steps"
    cam = SyntheticCamera(rig, "board-steps", frames=3, fps=1.0, seed=3)
    with cam, RecordingWriter(root, rig, cam.exposure_s) as writer:
        for frame in cam.frames():
            assert writer.write(frame)
    return root


@pytest.fixture(scope="module")
def webcam_steps(tmp_path_factory) -> Path:
    """The same board seen by a camera storing ``light ** (1 / 2.2)`` (a webcam)."""
    rig = load_rig(RIG_FILE).scaled(0.5)
    root = tmp_path_factory.mktemp("webcam") / "steps"
    cam = SyntheticCamera(rig, "board-steps", frames=3, fps=1.0, seed=3,
                          sensor=SensorModel(camera_gamma=2.2))  # fmt: skip
    with cam, RecordingWriter(root, rig, cam.exposure_s) as writer:
        for frame in cam.frames():
            assert writer.write(frame)
    return root


def test_camera_response_from_still_lines(steps, webcam_steps):
    """Measured: 2.24 for the webcam (its lines 0.42 px wider at half height when taken as
    linear), 1.017 for the linear camera (0.013 px), written as exactly 1."""
    rec = read_recording(webcam_steps)
    webcam = measure_response(rec.rig, recording_frames(rec))
    print(f"\nwebcam {webcam}")
    assert webcam.gamma == pytest.approx(2.2, abs=0.1)
    assert webcam.excess_linear_px > 0.3 and webcam.lines > 10_000
    rec = read_recording(steps)
    linear = measure_response(rec.rig, recording_frames(rec))
    print(f"linear {linear}")
    assert linear.gamma == 1.0 and abs(linear.measured - 1.0) < 0.03
    assert abs(linear.excess_linear_px) < 0.05


def test_rig_blur_writes_the_webcam_gamma_and_its_true_blur(webcam_steps, tmp_path, capsys):
    out = tmp_path / "webcam.json"
    assert main(["rig", "blur", str(webcam_steps), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "camera response: gamma 2.2" in text and "not linear" in text
    rig = load_rig(out)
    assert rig.camera.gamma == pytest.approx(2.2, abs=0.1)
    # measured on linearised frames, the blur is the simulator's (as for a linear camera)
    for p, (_, pat) in enumerate(rig.patterns):
        a, b = pat.blur
        for m in (1.0, 2.0):
            assert math.sqrt(a + b * m * m) == pytest.approx(truth_sigma(m), rel=0.08), p


def test_blur_from_still_lines_matches_the_simulated_optics(steps):
    rec = read_recording(steps)
    blurs = measure_blur(rec.rig, recording_frames(rec))
    assert len(blurs) == 2
    for pb in blurs:
        lo, hi = pb.magnification
        assert hi > 1.3 * lo  # three depths: the two parts can be told apart
        for m in (lo, hi):
            # measured 1-5 % low at the smallest magnification, within 1 % at the largest
            assert pb.sigma_px(m) == pytest.approx(truth_sigma(m), rel=0.07)
        assert pb.lines > 10_000


def test_rig_blur_writes_a_rig_whose_blur_the_pipeline_uses(steps, tmp_path, capsys):
    out = tmp_path / "rig-blur.json"
    assert main(["rig", "blur", str(steps), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "pattern 1" in text and "pattern 2" in text and "wrote" in text
    doc = json.loads(out.read_text())
    blur = doc["projectors"][0]["patterns"][0]["blur"]
    assert set(blur) == {"camera_px2", "projector_px2"}
    rig = load_rig(out)
    base = load_rig(RIG_FILE)
    assert rig.crosstalk is not None
    assert rig.geometry_digest() == base.scaled(0.5).geometry_digest()  # same depth table
    model = FlowModel(rig)
    assert model.calibrated and model.fitted
    assert not model.refits_at(0, FlowParams())  # never refitted
    np.testing.assert_allclose(model.blur[0], [blur["camera_px2"], blur["projector_px2"]])


def simulated_crosstalk(rig) -> list[float]:
    """Per pattern, the share of the other pattern's light its channel sees in the simulator."""
    from lightflow.app.core.rig import CHANNEL_INDEX

    xt = np.asarray(SensorModel().crosstalk)
    a, b = (CHANNEL_INDEX[pat.channel] for _, pat in rig.patterns)
    return [float(xt[a, b]), float(xt[b, a])]


def test_crosstalk_from_still_lines_matches_the_simulated_camera(steps):
    """Measured 0.0399 and 0.0313 against the simulator's 0.04 and 0.03 (both directions:
    the dense pattern's channel too, whose gaps are narrower than a sparse band with its
    floor)."""
    rec = read_recording(steps)
    measured = measure_crosstalk(rec.rig, recording_frames(rec))
    print(f"\ncrosstalk {measured}, simulated {simulated_crosstalk(rec.rig)}")
    assert measured == pytest.approx(simulated_crosstalk(rec.rig), abs=0.003)


def test_rig_blur_writes_the_crosstalk_that_the_pipeline_then_subtracts(steps, tmp_path, capsys):
    out = tmp_path / "rig-crosstalk.json"
    assert main(["rig", "blur", str(steps), "--out", str(out)]) == 0
    assert "colour crosstalk: the red channel sees" in capsys.readouterr().out
    rig = load_rig(out)
    assert rig.crosstalk == pytest.approx(simulated_crosstalk(rig), abs=0.003)
    # the moving frames of a 300 ms board show few clean gaps: the rig's crosstalk is used
    # from the first frame on, and never replaced by the frames' estimates
    cam = SyntheticCamera(rig, "slow-board", frames=2)
    pipeline = DepthPipeline(rig, PipelineConfig())
    with cam:
        for frame in cam.frames():
            result = pipeline.process(frame)
            assert result.leak_known
            np.testing.assert_allclose(pipeline.state()["pipeline"]["_leak"], rig.crosstalk)
    # a number given as the option still wins
    fixed = DepthPipeline(rig, PipelineConfig(crosstalk=0.01))
    assert fixed.state()["pipeline"]["_leak_known"].sum() == 0


def rig_check_error(tmp_path, capsys, field, value):
    """``lightflow rig check`` on the example rig with its first pattern's ``field`` set to
    ``value``: exit status 2 and one line on stderr, which is returned."""
    doc = json.loads(RIG_FILE.read_text())
    doc["projectors"][0]["patterns"][0][field] = value
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(doc))
    status = main(["rig", "check", str(path)])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(err) == 1
    return err[0]


@pytest.mark.parametrize("value", [-0.01, 0.2, "0.04"])
def test_bad_crosstalk_field_is_one_line(value, tmp_path, capsys):
    err = rig_check_error(tmp_path, capsys, "crosstalk", value)
    assert "patterns[0].crosstalk" in err and "expected" in err


def test_rig_blur_on_moving_lines_is_one_line(tmp_path, capsys):
    rig = load_rig(RIG_FILE).scaled(0.25)
    root = tmp_path / "moving"
    cam = SyntheticCamera(rig, "board", frames=1, exposure_s=0.03)
    with cam, RecordingWriter(root, rig, cam.exposure_s) as writer:
        for frame in cam.frames():
            assert writer.write(frame)
    status = main(["rig", "blur", str(root), "--out", str(tmp_path / "x.json")])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(err) == 1
    assert "too few static lines" in err[0]
    assert not (tmp_path / "x.json").exists()


def test_bad_blur_field_is_one_line(tmp_path, capsys):
    err = rig_check_error(tmp_path, capsys, "blur", {"camera_px2": 0.3, "projector_px2": -1})
    assert "patterns[0].blur.projector_px2" in err and "expected 0 or more" in err
