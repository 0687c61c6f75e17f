"""``lightflow demo``: its scene, its accuracy lines and its options (the streaming run is
tested in test_simulate.py)."""

from __future__ import annotations

import types

import numpy as np
import pytest

from lightflow.app.cli import main as cli_main
from lightflow.app.commands.demo import AccuracySink, simulated_crosstalk
from lightflow.app.core.rig import resolve_rig
from lightflow.app.evaluation import evaluate_frame
from lightflow.drivers.sim.scenes import get_scene
from lightflow.drivers.sim.synthetic import GroundTruth, SceneRenderer


def test_demo_scene_has_two_boards_moving_apart_before_a_static_wall():
    scene = get_scene("boards-wall")
    assert scene.objects == ("left board", "right board") and scene.planar
    rig = resolve_rig("two-projector").scaled(0.1)
    renderer = SceneRenderer(rig, scene)
    a, b = renderer.truth(0.1), renderer.truth(0.2)
    wall, left, right = (a.object_id == k for k in (1, 2, 3))
    assert 0.2 < wall.mean() and 0.05 < left.mean() < 0.5 and 0.05 < right.mean() < 0.5
    assert np.allclose(a.depth[wall], 1.1, atol=1e-4)
    assert np.allclose(b.depth[b.object_id == 1], 1.1, atol=1e-4)
    assert np.median(np.nonzero(left)[1]) < np.median(np.nonzero(right)[1])
    # along the axis at 0.6 m/s, in opposite directions: 60 mm in 0.1 s, within 0.6-0.9 m
    for obj, step in ((2, 0.06), (3, -0.06)):
        za, zb = (float(np.median(t.depth[t.object_id == obj])) for t in (a, b))
        assert 0.6 <= min(za, zb) and max(za, zb) <= 0.9
        assert zb - za == pytest.approx(step, abs=0.005)


def _result(depth, truth):
    frame = types.SimpleNamespace(extras={"truth": truth})
    return types.SimpleNamespace(depth=depth, frame=frame)


def test_accuracy_lines_use_eval_coverage_and_count_frames_with_depth():
    h, w = 20, 30
    ids = np.ones((h, w), np.uint8)
    ids[:, :10] = 2  # the board: 200 pixels
    ids[:5, 20:] = 3  # the ball: 50 pixels
    lit = np.full((h, w), 3, np.uint8)
    lit[:, 9] = 1  # one column of the board lit by one projector only: not counted
    truth = GroundTruth(np.full((h, w), 0.7, np.float32), ids, lit, False)
    depth = np.full((h, w), np.nan, np.float32)
    depth[:10, :10] = 0.71  # half the board, 10 mm too far
    depth[:5, 20:25] = 0.69  # half the ball, 10 mm too near
    sink = AccuracySink(2, ("board", "ball"))
    sink.write(_result(depth, truth), None)
    sink.write(_result(np.full((h, w), np.nan, np.float32), truth), None)  # no depth
    sink.write(types.SimpleNamespace(depth=depth, frame=types.SimpleNamespace(extras={})), None)
    expected = evaluate_frame(depth, truth, n_projectors=2)
    assert expected.n_target == 180 + 50 and expected.n_covered == 90 + 25
    assert sink.frames_with_depth == 1 and len(sink.per_frame) == 2
    lines = sink.describe()
    assert lines[0] == (
        "frames with depth on the moving objects: 1 of 2 (1 with at least 10 % coverage)"
    )
    # pooled over both frames: 115 of 460 target pixels; board 90 of 360, ball 25 of 100
    assert "median error 10.0 mm" in lines[1]
    assert "coverage 25 % (board 25 %, ball 25 %)" in lines[1]
    assert "every projector lights" in lines[2]


def test_no_depth_at_all_is_said_plainly():
    truth = GroundTruth(np.full((4, 4), 0.7, np.float32), np.full((4, 4), 2, np.uint8),
                        np.full((4, 4), 3, np.uint8), True)  # fmt: skip
    sink = AccuracySink(2)
    sink.write(_result(np.full((4, 4), np.nan, np.float32), truth), None)
    assert sink.describe() == [
        "frames with depth on the moving objects: 0 of 1 (0 with at least 10 % coverage)",
        "accuracy: no depth on the moving objects (coverage 0 %)",
    ]


def test_leak_is_the_simulated_cameras_per_pattern():
    # SensorModel: red gets 0.04 of the blue light, blue 0.03 of the red
    rig = resolve_rig("two-projector")
    channels = [pat.channel for _, pat in rig.patterns]
    leaks = dict(zip(channels, simulated_crosstalk(rig), strict=True))
    assert leaks == {"red": pytest.approx(0.04), "blue": pytest.approx(0.03)}


@pytest.mark.parametrize("value", ["-0.1", "lots", "0.7"])
def test_bad_crosstalk_is_one_line(value, capsys):
    assert cli_main(["demo", "--no-viewer", "--crosstalk", value, "--frames", "1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lightflow: error: --crosstalk") and err.count("\n") == 1
