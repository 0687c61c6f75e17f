"""The renderer's true flows, and the stage-by-stage attribution of `eval --stages`."""

from __future__ import annotations

import numpy as np
import pytest

from lightflow.app.commands.simulate import simulate_recording
from lightflow.app.core.errors import ConfigError
from lightflow.app.core.geometry import camera_rays, project_to_projector
from lightflow.app.core.rig import resolve_rig
from lightflow.app.evaluation import evaluate_recording
from lightflow.app.stages import FLOWS_SUFFIX, TrueFlows, format_stages
from lightflow.drivers.sim.synthetic import GroundTruth


@pytest.fixture(scope="module")
def board(tmp_path_factory):
    rig = resolve_rig("two-projector").scaled(0.5)
    out = tmp_path_factory.mktemp("stages") / "board"
    simulate_recording(rig, "board", out, frames=2, exposure_s=0.02, truth_flows=True)
    return rig, out


def test_true_flows_match_the_core_geometry(board):
    """Flows from OpenCV's projection agree with the core's lens model on the moving board.

    The board moves along the optical axis, so the flow of a pixel is the change of
    its projector column between the depths at the start and the end of the exposure.
    """
    rig, out = board
    flows = TrueFlows.load(out / "ground_truth" / f"000000{FLOWS_SUFFIX}")
    truth = GroundTruth.load(out / "ground_truth" / "000000.npz")
    on = np.isfinite(flows.flow).all(axis=0)
    assert on.mean() > 0.5  # the board fills most of the image
    # the board's speed (0.6 m/s, drivers/scenes.py) over the exposure, along z
    rays = camera_rays(rig.camera)
    dz = 0.6 * 0.02
    for q, (proj, pat) in enumerate(rig.patterns):
        z = truth.depth[..., None].astype(np.float64)
        u0 = project_to_projector(proj, rays * (z - dz / 2))[..., 0]
        u1 = project_to_projector(proj, rays * (z + dz / 2))[..., 0]
        expected = np.abs(u1 - u0)[on]
        rel = np.abs(flows.flow[q][on] / expected - 1)
        assert np.median(rel) < 0.01, np.median(rel)
        # the interval is the pitch over the projector columns per camera column
        assert np.all(flows.interval[q][on] > 0)
        line_over_interval = flows.line[q][on] / flows.interval[q][on]
        assert np.allclose(line_over_interval, pat.width_px / pat.pitch_px, rtol=1e-4)


def test_eval_stages_traces_a_board_to_accurate_flows(board, capsys):
    """On a board every stage is right (measured: flows within 0.8 %, log ratio 0.005, depth
    -4.8 mm): each within about twice that."""
    _rig, out = board
    m = evaluate_recording(out, stages=True)
    s = m.stages
    assert s["n"] > 1000
    for p in range(2):
        assert abs(s[f"flow{p}_signed_pct"]) < 2.0, s
        assert s[f"flow{p}_abs_pct"] < 2.0, s
        assert s[f"sweep{p}_px"] > 2.0
    assert abs(s["log_ratio"]) < 0.015, s
    assert abs(s["depth_mm"]) < 8.0, s
    line = format_stages("board", s)
    assert "pattern 0" in line and "log ratio" in line


def test_true_flows_file_errors_are_one_line(tmp_path):
    bad = tmp_path / f"000000{FLOWS_SUFFIX}"
    np.savez(bad, sweep=np.zeros((2, 4, 4)))
    with pytest.raises(ConfigError, match="expected true flows"):
        TrueFlows.load(bad)
