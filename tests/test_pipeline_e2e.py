"""End to end: render synthetic scenes, reconstruct them, compare with the ground truth.

Half-resolution rigs (800x600), analysis stride 4.  The measured numbers are
printed (``pytest -s``) so that the margins are visible.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from lightflow.app.core.errors import ConfigError, FrameError
from lightflow.app.core.flow import FlowParams
from lightflow.app.core.pipeline import DepthPipeline, PipelineConfig
from lightflow.app.core.rig import load_rig
from lightflow.drivers.base import Frame
from lightflow.drivers.sim.scenes import get_scene
from lightflow.drivers.sim.synthetic import GroundTruth, SceneRenderer, SyntheticCamera

RIGS = Path(__file__).resolve().parents[1] / "app" / "rigs"
STRIDE = 4


@pytest.fixture(scope="module")
def rig2():
    return load_rig(RIGS / "two-projector.json").scaled(0.5)


@pytest.fixture(scope="module")
def rig1():
    return load_rig(RIGS / "single-projector.json").scaled(0.5)


def run(rig, scene, frames, exposure_s=None, stride=STRIDE):
    """Render ``frames`` frames of ``scene`` and reconstruct them with a fresh pipeline."""
    pipe = DepthPipeline(rig, PipelineConfig(stride=stride))
    out = []
    with SyntheticCamera(rig, scene, frames=frames, exposure_s=exposure_s, seed=0) as cam:
        for frame in cam.frames():
            out.append((frame.extras["truth"], pipe.process(frame)))
    assert len(out) == frames
    return out


def scores(rig, truth, result, label):
    """Error and coverage numbers of one frame (printed)."""
    depth = result.depth
    cam = rig.camera
    assert depth.shape == (cam.height, cam.width) and depth.dtype == np.float32
    has = np.isfinite(depth)
    moving = truth.object_id >= 2
    all_lit = (1 << len(rig.projectors)) - 1
    lit = (truth.lit & all_lit) == all_lit
    target = moving & lit
    err = np.abs(depth - truth.depth)[has & moving]
    s = {
        "median_mm": float(np.median(err)) * 1e3 if err.size else np.inf,
        "p90_mm": float(np.percentile(err, 90)) * 1e3 if err.size else np.inf,
        "coverage": float(np.count_nonzero(has & target) / max(1, np.count_nonzero(target))),
        "off_object_px": int(np.count_nonzero(has & ~moving)),
        "off_fraction": float(np.count_nonzero(has & ~moving) / max(1, np.count_nonzero(has))),
        "depth_px": int(np.count_nonzero(has)),
        "moving_px": int(np.count_nonzero(moving)),
    }
    print(f"\n{label}: median |dz| {s['median_mm']:.2f} mm, p90 {s['p90_mm']:.2f} mm, "
          f"coverage {s['coverage']:.3f} of moving&lit, {s['depth_px']} depth px, "
          f"{s['off_object_px']} off the moving object ({100 * s['off_fraction']:.2f} % of depth), "
          f"result.coverage {result.coverage:.3f}, "
          f"total {result.timings_ms.get('total', np.nan):.0f} ms")  # fmt: skip
    return s


@pytest.fixture(scope="module")
def board_two_projector(rig2):
    return run(rig2, "board", frames=2)


def test_board_two_projector(rig2, board_two_projector):
    for i, (truth, result) in enumerate(board_two_projector):
        s = scores(rig2, truth, result, f"board, two-projector, frame {i}")
        assert s["median_mm"] < 10.0
        assert s["coverage"] > 0.83  # 0.889 and 0.844 measured
        assert s["off_object_px"] == 0
        # no depth where there is no surface at all
        assert not np.any(np.isfinite(result.depth) & np.isnan(truth.depth))
        assert result.log_ratio_grid.shape == (rig2.camera.height // STRIDE,
                                               rig2.camera.width // STRIDE)  # fmt: skip
        assert len(result.flows_grid) == 2 and len(result.bands) == 2


def test_board_single_projector(rig1):
    ((truth, result),) = run(rig1, "board", frames=1)
    s = scores(rig1, truth, result, "board, single-projector")
    assert s["median_mm"] < 10.0
    assert s["off_object_px"] == 0


def test_still_board_single_projector_gets_depth_from_the_intervals(rig1):
    """One projector: the depth is in the ratio of the line intervals, with no motion."""
    scene = get_scene("still-board")
    renderer = SceneRenderer(rig1, scene)
    image = renderer.expose(renderer.radiance(0.0, scene.exposure_s), np.random.default_rng(0))
    truth = renderer.truth(0.0)
    results = {}
    for mode in ("auto", "off"):
        cfg = PipelineConfig(stride=STRIDE, flow=FlowParams(static_depth=mode))
        results[mode] = DepthPipeline(rig1, cfg).process(Frame(0, 0.0, scene.exposure_s, image))
    s = scores(rig1, truth, results["auto"], "still board, single-projector, static depth")
    # measured: median 4.1 mm, coverage 0.94, 0.03 % of the depth off the board
    assert s["median_mm"] < 7.0
    assert s["coverage"] > 0.85
    assert s["off_fraction"] <= 0.02
    assert np.isnan(results["off"].depth).all()  # without the mode: static lines, no depth


def test_blur_measured_on_the_wall_behind_a_fan(rig2):
    """The wall's lines stand still from frame to frame: the blur comes from them.

    The simulator's optics: sigma^2 = 0.36 + 0.36 m^2 (camera px, m the magnification).
    """
    pipe = DepthPipeline(rig2, PipelineConfig(stride=STRIDE))
    model = pipe.flow_model
    with SyntheticCamera(rig2, "fan-1ms", frames=3, seed=0) as cam:
        for frame in cam.frames():
            pipe.process(frame)
            if frame.index == 0:
                assert model.blur_source == "moving bands"
    assert model.blur_source == "still lines"
    for m in (1.0, 2.0):
        sigma = np.sqrt(model.blur[0, 0] + model.blur[0, 1] * m * m)
        # measured: 0.86 and 1.43 px against 0.85 and 1.34
        assert sigma == pytest.approx(np.sqrt(0.36 + 0.36 * m * m), rel=0.1)
    assert not model.refits_at(30, FlowParams())


def test_static_depth_on_is_refused_with_two_projectors(rig2):
    with pytest.raises(ConfigError, match="static_depth"):
        DepthPipeline(rig2, PipelineConfig(stride=STRIDE, flow=FlowParams(static_depth="on")))
    with pytest.raises(ConfigError, match="static_depth"):
        FlowParams(static_depth="yes")


def test_tilted_board_two_projector(rig2):
    ((truth, result),) = run(rig2, "tilted-board", frames=1)
    s = scores(rig2, truth, result, "tilted-board, two-projector")
    assert s["moving_px"] < truth.object_id.size  # the board does not fill the image
    assert s["median_mm"] < 15.0
    assert s["off_fraction"] <= 0.02


def test_fan_static_wall_gets_no_depth(rig2):
    ((truth, result),) = run(rig2, "fan", frames=1)
    s = scores(rig2, truth, result, "fan, two-projector, nominal exposure")
    wall = truth.object_id == 1
    assert wall.mean() > 0.5  # most of the image is the static wall
    # the blades are measured at all, so that the check below is not vacuous (2480 px
    # measured: the uncertain blade tips get none)
    assert s["depth_px"] - s["off_object_px"] > 1500
    assert s["off_fraction"] <= 0.02


def test_static_scene_gets_almost_no_depth(rig2):
    """The board with a 0.1 ms exposure (sweep 0.06 mm), brightened to its nominal level.

    ``SyntheticCamera(..., exposure_s=1e-4)`` alone would scale the light down
    with the exposure (the frame peaks at ~5 DN and has no bands at all); here
    the radiance is rescaled so that every line is clearly visible but static.
    """
    scene = get_scene("board")
    renderer = SceneRenderer(rig2, scene)
    exposure = 1e-4
    radiance = renderer.radiance(0.1, exposure) * (scene.exposure_s / exposure)
    image = renderer.expose(radiance, np.random.default_rng(0))
    pipe = DepthPipeline(rig2, PipelineConfig(stride=STRIDE))
    result = pipe.process(Frame(0, 0.1, exposure, image))
    valid_bands = [int(b.valid.sum()) for b in result.bands]
    frac = float(np.mean(np.isfinite(result.depth)))
    print(f"\nstatic board: peak {image.max()} DN, valid bands {valid_bands}, "
          f"depth on {100 * frac:.3f} % of the pixels")  # fmt: skip
    assert min(valid_bands) > 1000  # the lines are seen ...
    assert frac < 0.01  # ... but nothing moves


def test_frame_of_wrong_size_is_refused(rig2):
    pipe = DepthPipeline(rig2, PipelineConfig(stride=STRIDE))
    frame = Frame(3, 0.0, 0.02, np.zeros((300, 400, 3), np.uint8))
    with pytest.raises(FrameError) as info:
        pipe.process(frame)
    msg = str(info.value)
    print(f"\nwrong size: {msg}")
    assert "400x300" in msg and "800x600" in msg


def test_twelve_bit_camera_gives_the_same_depth(rig2, board_two_projector):
    """Mono12-style data (uint16 values 0..4095, bits=12) measures like the 8-bit frame."""
    truth, result8 = board_two_projector[0]
    frame8 = result8.frame
    image12 = np.round(frame8.image.astype(np.float64) * (4095 / 255)).astype(np.uint16)
    frame12 = Frame(frame8.index, frame8.timestamp, frame8.exposure_s, image12, bits=12)
    # a fresh pipeline for each, so the learnt state (colour leak, windows) matches
    pipe8 = DepthPipeline(rig2, PipelineConfig(stride=STRIDE))
    pipe12 = DepthPipeline(rig2, PipelineConfig(stride=STRIDE))
    d8 = pipe8.process(frame8).depth
    d12 = pipe12.process(frame12).depth
    both = np.isfinite(d8) & np.isfinite(d12)
    assert np.count_nonzero(np.isfinite(d12)) >= 0.98 * np.count_nonzero(np.isfinite(d8))
    # within noise: the blur fit sees the 12-bit rounding (a few 0.1 mm here)
    assert np.median(np.abs(d8[both] - d12[both])) < 1e-3
    # read as full-range 16-bit instead, the same data would lose most bands
    frame16 = Frame(frame8.index, frame8.timestamp, frame8.exposure_s, image12)
    d16 = DepthPipeline(rig2, PipelineConfig(stride=STRIDE)).process(frame16).depth
    assert np.count_nonzero(np.isfinite(d16)) < 0.5 * np.count_nonzero(np.isfinite(d8))


# ------------------------------------------------------------------ unseen rigs, paper exposures


def _generated_rig(left, right, fcam=1700.0, crop=(640, 480, 480, 360)):
    """A two-projector rig that is not in the repository, seen through a crop of its
    1600x1200 camera (full-resolution bands at a fraction of the rendering cost).

    ``left``/``right``: (centre in camera coordinates, toe-in in degrees, focal
    length, pitch) of each projector; toe-in turns it towards the optical axis.
    """
    import math

    from lightflow.app.core.rig import rig_from_dict

    def proj(name, centre, toe, f, pitch, channel):
        c = np.asarray(centre, float)
        th = math.radians(toe) * -np.sign(c[0])
        z = np.array([math.sin(th), 0.0, math.cos(th)])
        R = np.stack([np.cross([0.0, 1.0, 0.0], z), [0.0, 1.0, 0.0], z])
        return {"name": name, "width": 1280, "height": 800,
                "K": [[f, 0, 639.5], [0, f, 399.5], [0, 0, 1]], "dist": [0, 0, 0, 0, 0],
                "R": R.tolist(), "t": (-R @ c).tolist(),
                "patterns": [{"channel": channel, "kind": "uniform", "pitch_px": pitch,
                              "width_px": 3.0, "offset_px": 0.0}]}  # fmt: skip

    w, h, x0, y0 = crop
    cam = {"width": w, "height": h, "dist": [0, 0, 0, 0, 0],
           "K": [[fcam, 0, 799.5 - x0], [0, fcam, 599.5 - y0], [0, 0, 1]]}  # fmt: skip
    return rig_from_dict({"format": "lightflow-rig/1", "camera": cam, "projectors": [
        proj("left", left[0], *left[1:], "red"), proj("right", right[0], *right[1:], "blue")]})


def _signed_scores(rig, scene, exposure_s, frames=2, stride=STRIDE):
    """Pooled median |error|, median signed error (mm), coverage, off-object share."""
    pipe = DepthPipeline(rig, PipelineConfig(stride=stride))
    errs, covered, target, depth_px, off = [], 0, 0, 0, 0
    with SyntheticCamera(rig, scene, frames=frames, fps=10, exposure_s=exposure_s) as cam:
        for frame in cam.frames():
            truth, result = frame.extras["truth"], pipe.process(frame)
            has = np.isfinite(result.depth)
            moving = truth.object_id >= 2
            tgt = moving & (truth.lit == 3)
            errs.append((result.depth - truth.depth)[has & moving] * 1e3)
            covered += int(np.count_nonzero(has & tgt))
            target += int(np.count_nonzero(tgt))
            depth_px += int(np.count_nonzero(has))
            off += int(np.count_nonzero(has & ~moving))
    e = np.concatenate(errs)
    s = {"median_mm": float(np.median(np.abs(e))), "signed_mm": float(np.median(e)),
         "coverage": covered / max(1, target), "off_fraction": off / max(1, depth_px)}  # fmt: skip
    print(f"\n{scene} {exposure_s * 1e3:g} ms, unseen rig: median |dz| {s['median_mm']:.2f} mm, "
          f"signed {s['signed_mm']:+.2f} mm, coverage {s['coverage']:.3f}, "
          f"off-object {100 * s['off_fraction']:.2f} %")  # fmt: skip
    return s


def test_tilted_board_moving_diagonally_unbiased_on_an_unseen_rig():
    """The issue's diagonal board (+19 mm of pure bias on an independent rig).

    Measured: median 0.07 mm, signed -0.06 mm, coverage 0.985, the depth triangulated
    (:mod:`lightflow.app.core.triangulation`); the flows alone: median 2.9 mm, signed
    -2.7 mm, coverage 0.98.  Before runs of valid bands
    with gaps under 3 blur sigmas were measured on their periodic profile
    (:data:`lightflow.app.core.overlap.TIGHT_GAP_SIGMAS`): 2.2 mm, -1.3 mm (their short
    reading partly cancelled another bias, which the stage trace has not yet named); before
    the tails of narrow gaps were subtracted: 3.3 mm, +2.4 mm; before the blur fit from
    short bands and the joint width/ramp sweeps: 9.6 mm, all of it bias, +9.6 mm.
    """
    rig = _generated_rig(((-0.30, 0.05, 0.30), 32, 1100, 28), ((0.38, -0.03, -0.22), 15, 1300, 20))
    s = _signed_scores(rig, "tilted-board", 0.02)
    assert s["median_mm"] <= 0.3
    assert abs(s["signed_mm"]) <= 0.2
    assert s["coverage"] >= 0.95


def test_fan_at_1ms_unbiased_on_an_unseen_rig():
    """Fan at the paper's 1 ms on a rig with a projector in front of the camera plane.

    Measured here: median 0.14 mm, signed -0.13 mm, coverage 0.954, 2.35 % off the fan
    (the blade's depth on the wall just past its edges: before the gaps in a line's
    trace were filled, 0.934 and 1.16 %; the fill closes one-row holes between bands past
    the blade's tip that the vertical passes had already given the blade's lines, and the
    cells between them follow), the depth triangulated and
    carried past the moving cells along the blades (chains of at most 8 bands: 0.891,
    0.65 %; before any: 0.13 mm, -0.13 mm, 0.529, 0.2 %).  The flows alone: median 2.0 mm, signed
    -1.2 mm, coverage 0.527 (where the lines move too
    little for a flow, the depth from the two line intervals, and averaged with the flow's
    where both are; without it: 4.5 mm, -3.9 mm, 0.312).  The second frame uses the
    blur measured on the wall's still lines, and its shorter static limit; before that
    limit: 4.6 mm, -2.4 mm, 0.237.  Before the tails of
    narrow gaps were subtracted and max_depth_std went to 5 %: 3.0 mm, -0.04 mm, 0.152;
    before the print fill (:func:`lightflow.app.core.bands.fill_print`): 7.2 mm, -7.2 mm,
    0.123.  Before the blur fit
    gain (chosen on the tuning rigs, where it moved every signed error towards 0, here
    past it): 3.3 mm, +2.0 mm, 0.175; before pixels with a predicted error over 3 % of the
    depth got none: 6.8 mm, +6.5 mm, 0.26; before the blur fit from short bands and the
    joint width/ramp sweeps: 16.6 mm, signed +16.6 mm.
    """
    rig = _generated_rig(((-0.25, 0.0, 0.35), 35, 1200, 36), ((0.42, 0.02, -0.20), 16, 1500, 16),
                         crop=(640, 640, 960, 280))  # fmt: skip
    s = _signed_scores(rig, "fan", 0.001)
    assert s["median_mm"] <= 0.5
    assert abs(s["signed_mm"]) <= 0.4
    assert s["coverage"] >= 0.94
    assert s["off_fraction"] <= 0.025


#: two rigs not in the repository: the tilted board's and the fan's
UNSEEN_RIGS = {
    "behind": (((-0.30, 0.05, 0.30), 32, 1100, 28), ((0.38, -0.03, -0.22), 15, 1300, 20)),
    "in front": (((-0.25, 0.0, 0.35), 35, 1200, 36), ((0.42, 0.02, -0.20), 16, 1500, 16)),
}


@pytest.mark.parametrize("name,median_mm,coverage",
                         [("behind", 0.4, 0.37), ("in front", 1.0, 0.65)])
def test_ball_thrown_at_5ms_on_two_unseen_rigs(name, median_mm, coverage):
    """The paper's ball thrown toward the camera at 5 ms, its depth triangulated.

    Measured here: median 0.15 mm, signed +0.09 mm, coverage 0.405 ("behind"); 0.64 mm,
    +0.14 mm, 0.709 ("in front", where the flows' depth stands on more of the limb).
    Before the triangulated depth reached past the moving cells and its runs were
    carried on to the limb: 0.15 mm, +0.07 mm, 0.335; 1.55 mm, +0.14 mm, 0.631.
    """
    rig = _generated_rig(*UNSEEN_RIGS[name])
    s = _signed_scores(rig, "ball-toward", 0.005)
    assert s["median_mm"] <= median_mm
    assert abs(s["signed_mm"]) <= 0.5
    assert s["coverage"] >= coverage
    assert s["off_fraction"] <= 0.02


def test_the_fast_grid_keeps_the_accuracy(rig2):
    """Stride 8 (every 8th row and column: about half the CPU of stride 4).  Measured
    here: the board 0.06 mm on 0.994 and 0.997 of it (stride 4: the same, 0.996 and
    0.998); the ball toward the camera at 5 ms on an unseen rig 0.14 mm, signed +0.10 mm,
    but on 0.403 of it (stride 4: 0.16 mm, +0.07 mm on 0.769): the coarser grid loses
    most where an object is small in the image."""
    for i, (truth, result) in enumerate(run(rig2, "board", 2, stride=8)):
        s = scores(rig2, truth, result, f"board, stride 8, frame {i}")
        assert result.depth_grid.shape == (rig2.camera.height // 8, rig2.camera.width // 8)
        assert s["median_mm"] < 0.2
        assert s["coverage"] > 0.98
        assert s["off_object_px"] == 0
    s = _signed_scores(_generated_rig(*UNSEEN_RIGS["in front"]), "ball-toward", 0.005, stride=8)
    assert s["median_mm"] <= 0.3
    assert abs(s["signed_mm"]) <= 0.3
    assert s["coverage"] >= 0.35
    assert s["off_fraction"] <= 0.02


def test_fan_at_1ms_with_a_measured_blur_on_an_unseen_rig():
    """The same fan with the blur in the rig, 5 % above the simulator's (as ``lightflow rig
    blur`` measures it: within 1-6 %), so that sweeps shorter than the line count.

    Measured here: median 0.14 mm, signed -0.13 mm, coverage 0.947, 2.24 % off the fan
    (0.934 and 1.18 % before the gaps in a line's trace were filled: see
    :func:`test_fan_at_1ms_unbiased_on_an_unseen_rig`), the depth triangulated (0.894
    with chains of at most 8 bands, 0.529 before it reached past the moving cells).  The
    flows alone: median 2.0 mm, signed -1.1 mm, coverage 0.528 (with
    the depth from the intervals; without it 3.8 mm, -2.7 mm, 0.405;
    the true blur then: 2.5 mm, +1.0 mm, 0.427; 5 % below it: 5.3 mm, +5.2 mm, 0.442).
    """
    rig = _generated_rig(((-0.25, 0.0, 0.35), 35, 1200, 36), ((0.42, 0.02, -0.20), 16, 1500, 16),
                         crop=(640, 640, 960, 280))  # fmt: skip
    # the simulator's blur: sigma^2 = 0.36 + 0.36 m^2 (camera px^2, m the magnification)
    s = _signed_scores(rig.with_blur([(0.378, 0.378)] * 2), "fan", 0.001)
    assert s["median_mm"] <= 0.5
    assert abs(s["signed_mm"]) <= 0.4
    assert s["coverage"] >= 0.93
    assert s["off_fraction"] <= 0.025


def _within_sigma(truth, result):
    on = (np.isfinite(result.depth) & (truth.object_id >= 2) & np.isfinite(truth.depth)
          & np.isfinite(result.depth_std))  # fmt: skip
    err = np.abs(result.depth[on] - truth.depth[on])
    sd = result.depth_std[on]
    return float(np.mean(err <= sd)), float(np.mean(err <= 2 * sd)), int(on.sum())


def test_predicted_uncertainty_matches_the_errors(board_two_projector):
    """About 68 % of the depth errors lie within the predicted sigma, 95 % within 2 sigma."""
    truth, result = board_two_projector[-1]
    one, two, n = _within_sigma(truth, result)
    print(f"\nboard: {100 * one:.0f} % within 1 sigma, {100 * two:.0f} % within 2 sigma "
          f"({n} px), median sigma {1e3 * np.nanmedian(result.depth_std):.1f} mm")  # fmt: skip
    assert n > 10000
    # measured 96 % and 98 % (93 % before the triangulated runs were carried on past
    # their ends, 89 % before the detector knew the line width and blur): the prediction
    # is cautious on boards, whose triangulated depth is within 0.1 mm where it predicts
    # 0.03 % of the depth (about 0.2 mm); halving that floor leaves boards at 96 % and
    # takes the tuning fans from 84-87 % to 49-57 % (README, "Known gaps")
    assert 0.55 <= one <= 0.97
    assert two >= 0.85
    assert result.depth_std.dtype == np.float32
    assert np.array_equal(np.isfinite(result.depth_std), np.isfinite(result.depth))


def test_every_grid_pixel_has_one_cause(rig2):
    """Fan before a static wall: every pixel without depth is counted under one cause."""
    from lightflow.app.core import causes

    ((truth, result),) = run(rig2, "fan", frames=1)
    counts = result.cause_counts
    assert counts.sum() == result.causes_grid.size
    assert counts[causes.DEPTH] == np.count_nonzero(np.isfinite(result.depth_grid)
                                                    & (result.causes_grid == causes.DEPTH))
    s = STRIDE
    wall = truth.object_id[s // 2::s, s // 2::s] == 1
    wall_causes = causes.count_causes(result.causes_grid[: wall.shape[0], : wall.shape[1]][wall])
    print("\nfan, wall pixels by cause: " + causes.describe_counts(wall_causes))
    # measured: faint 42 % (the wall's lines in the blades' shadow and at its far side),
    # static 35 %, irregular 10 %, overlap 7 %
    assert wall_causes[causes.DEPTH] <= 0.02 * wall_causes.sum()
    assert wall_causes[[causes.STATIC, causes.FAINT]].sum() > 0.6 * wall_causes.sum()


def test_lines_wider_than_the_model_get_a_warning_and_a_cause():
    """Projected lines far wider than the profile tables: counted, and the frame warns why."""
    from lightflow.app.core import causes
    from lightflow.app.core.rig import rig_from_dict

    d = load_rig(RIGS / "two-projector.json").to_dict()
    for proj in d["projectors"]:
        for pat in proj["patterns"]:
            # 40 projector px lines at a 100 px pitch: over 20 camera px wide at half size
            pat["pitch_px"], pat["width_px"] = 100.0, 40.0
    rig = rig_from_dict(d, "thick lines").scaled(0.5)
    ((_, result),) = run(rig, "board", frames=1)
    counts = result.cause_counts
    lit = counts.sum() - counts[causes.NO_LINES]
    print(f"\nthick lines: {causes.describe_counts(counts)}; warnings {result.warnings}")
    assert counts[causes.MODEL_RANGE] > 0.5 * lit
    assert len(result.warnings) == 1
    assert "out of the model's range" in result.warnings[0]
    assert "lines wider than the profile tables" in result.warnings[0]


def test_printed_board_keeps_its_bands():
    """Issue 8 section 5: newspaper print cut every band (cause "cut") before the print fill.

    Measured here: median 5.0 mm, coverage 0.83; 4.6 mm on 0.77 before photo blocks got
    the long fill where lines stand upright (once 7.4 mm on 0.68, and 8.8 mm on 0.55
    without any fill).
    """
    rig = load_rig(RIGS / "two-projector.json").scaled(0.5)
    ((truth, result),) = run(rig, "newspaper-board", frames=1, exposure_s=0.3)
    s = scores(rig, truth, result, "newspaper")
    assert s["coverage"] >= 0.8
    assert s["median_mm"] <= 6.5
    assert s["off_object_px"] == 0


def test_a_camera_with_gamma_is_linearised_by_its_rig():
    """A camera storing ``light ** (1 / 2.2)`` (a webcam, an sRGB image) widens every band.

    Without its gamma the board moving diagonally at 300 ms reads long (the issue's
    one-sided bias); with the rig's ``camera.gamma`` every frame is linearised first and
    the depth is that of a linear camera.  Measured: gamma camera read as linear +68.0 mm
    (median 68.0 mm); linearised 3.45 mm, -3.43 mm; a linear camera 3.40 mm, -3.38 mm;
    coverage 1.00 in all three.
    """
    from lightflow.drivers.sim.synthetic import SensorModel

    rig = _generated_rig(((-0.30, 0.05, 0.30), 32, 1100, 28), ((0.38, -0.03, -0.22), 15, 1300, 20))

    def signed(rig_used, camera_gamma):
        pipe = DepthPipeline(rig_used, PipelineConfig(stride=STRIDE))
        errs, covered, target = [], 0, 0
        sensor = SensorModel(camera_gamma=camera_gamma)
        with SyntheticCamera(rig, "diagonal-board", frames=2, fps=10, exposure_s=0.3,
                             sensor=sensor) as cam:  # fmt: skip
            for frame in cam.frames():
                truth, result = frame.extras["truth"], pipe.process(frame)
                has = np.isfinite(result.depth)
                moving = truth.object_id >= 2
                errs.append((result.depth - truth.depth)[has & moving] * 1e3)
                covered += int(np.count_nonzero(has & moving & (truth.lit == 3)))
                target += int(np.count_nonzero(moving & (truth.lit == 3)))
        e = np.concatenate(errs)
        print(f"\ncamera gamma {camera_gamma}, rig's {rig_used.camera.gamma}: median "
              f"{np.median(np.abs(e)):.2f} mm, signed {np.median(e):+.2f} mm, "
              f"coverage {covered / target:.3f}")  # fmt: skip
        return float(np.median(np.abs(e))), float(np.median(e)), covered / target

    unknown = signed(rig, 2.2)
    known = signed(rig.with_camera_gamma(2.2), 2.2)
    linear = signed(rig, 1.0)
    assert unknown[1] > 40.0  # read long without the gamma
    assert abs(known[0] - linear[0]) <= 0.5 and abs(known[1] - linear[1]) <= 0.5
    assert known[0] <= 4.5 and known[2] >= 0.95


def test_a_webcam_fan_gets_its_gamma_from_the_wall_behind():
    """No gamma in the rig, ``camera_gamma="auto"``: the pipeline measures it on the wall's
    still lines between the first frames and linearises from the second frame on.

    Measured (frames 1-2 of 3, the fan at 1 ms before a wall, camera gamma 2.2): gamma
    2.16 from the wall; median 0.1 mm, signed -0.1 mm, 2.2 % off the object (1.5 % before
    the gaps in a line's trace were filled, 0.7 % before
    lines that moved between frames counted as moving and chains of bands grew longer than
    8); the same frames read as linear: 0.2 mm, -0.1 mm, but 75.2 % of the depth off the
    fan (23.8 % before; the wall's lines read as moving).  With the flows alone (before
    the twentieth session's triangulated depth): 1.9 mm, +0.3 mm measured, 33 mm, +33 mm
    read as linear.
    """
    from lightflow.drivers.sim.synthetic import SensorModel

    rig = _generated_rig(((-0.25, 0.0, 0.35), 35, 1200, 36), ((0.42, 0.02, -0.20), 16, 1500, 16),
                         crop=(640, 640, 960, 280))  # fmt: skip

    def scores(config):
        pipe = DepthPipeline(rig, config)
        errs, depth_px, off = [], 0, 0
        with SyntheticCamera(rig, "fan", frames=3, fps=10, exposure_s=0.001,
                             sensor=SensorModel(camera_gamma=2.2)) as cam:  # fmt: skip
            for i, frame in enumerate(cam.frames()):
                truth, result = frame.extras["truth"], pipe.process(frame)
                if i == 0:
                    continue  # read before the wall's lines could be compared
                has = np.isfinite(result.depth)
                moving = truth.object_id >= 2
                errs.append((result.depth - truth.depth)[has & moving] * 1e3)
                depth_px += int(np.count_nonzero(has))
                off += int(np.count_nonzero(has & ~moving))
        e = np.concatenate(errs)
        print(f"\n{pipe.gamma_source or 'no'} gamma {pipe.camera_gamma:.3f}: median "
              f"{np.median(np.abs(e)):.1f} mm, signed {np.median(e):+.1f} mm, off the object "
              f"{100 * off / max(1, depth_px):.1f} %")  # fmt: skip
        return pipe, float(np.median(np.abs(e))), float(np.median(e)), off / max(1, depth_px)

    pipe, median, signed, off = scores(PipelineConfig(stride=STRIDE, camera_gamma="auto"))
    assert pipe.gamma_source == "still lines" and pipe.camera_gamma == pytest.approx(2.2, abs=0.12)
    assert median <= 8.0 and abs(signed) <= 4.0 and off <= 0.025
    _, median_linear, signed_linear, off_linear = scores(
        PipelineConfig(stride=STRIDE, camera_gamma=1.0))
    # read as linear, the wall's still lines pass for moving ones: the triangulated depth
    # stays right where it is (0.2 mm), but the wall gets it too
    assert off_linear > 0.1


def _photo_page(slant: float, rng) -> np.ndarray:
    """An 800x600 page of upright (or slanted) bands of both patterns, under text and a
    photo block (rows 240-370, columns 200-600) of 13 px grey cells of albedo 0.2-0.8,
    seen through a lens blur of 0.8 px.

    Pattern 0 (red): interval 40 px, ramps 3 px, half-height width 15 px; pattern 1
    (blue): interval 24 px, half-height width 9 px.
    """
    h, w = 600, 800
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    xs = x - slant * (y - h / 2)

    def bands(interval, top):
        u = xs % interval
        return np.clip(np.minimum(u - 2.0, top - u) / 3.0, 0.0, 1.0)

    albedo = np.full((h, w), 0.92)
    # body text as in the scene: lines of glyphs 5 rows tall, 8 rows apart, 30 % ink
    for line in range(4, h - 8, 8):
        albedo[line : line + 5][rng.random((5, w)) < 0.3] = 0.12
    cells = rng.uniform(0.2, 0.8, (10, 31))
    albedo[240:370, 200:600] = np.kron(cells, np.ones((13, 13)))[:130, :400]
    img = np.zeros((h, w, 3))
    img[..., 0] = albedo * (12.0 + 200.0 * bands(40.0, 20.0))
    img[..., 2] = albedo * (12.0 + 200.0 * bands(24.0, 14.0))
    img[..., 1] = albedo * 12.0
    img = cv2.GaussianBlur(img, (0, 0), 0.8) + rng.normal(0.0, 1.0, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def _photo_bands(image, block_px):
    """Per pattern, the valid bands' lengths in the photo block's rows and columns (away
    from its edges), and their count there."""
    from lightflow.app.core import bands as bd
    from lightflow.app.core.bands import BandParams

    rig = load_rig(RIGS / "two-projector.json").scaled(0.5)
    pipe = DepthPipeline(rig, PipelineConfig(stride=STRIDE, bands=BandParams(
        print_block_px=block_px)))  # fmt: skip
    bands, counts, _ = pipe._measure(Frame(0, 0.0, 0.3, image, "page"), {})
    rows = (pipe._row_y > 245) & (pipe._row_y < 365)
    out = []
    for p in range(2):
        b = bands[p][rows]
        n = np.arange(b.shape[1])[None, :] < counts[p][rows][:, None]
        c = b[..., bd.F_CENTRE]
        keep = n & (b[..., bd.F_VALID] > 0) & (c > 215) & (c < 585)
        out.append(b[..., bd.F_LENGTH][keep])
    return out


def test_photo_block_keeps_its_bands_where_lines_stand_upright():
    """Issue 8: a newspaper's photo block (grey cells larger than the print fill's 13 rows)
    cut the bands under it.  Where there is print and the lines stand upright, dips up
    to 81 rows are filled too, and the block's rows measured again.

    Measured here: valid bands in the block 187 and 335 -> 261 and 463 (of 261 and 464
    lines), median lengths 15.11 and 9.05 px (true 15 and 9), 90th percentile of the
    length error 1.04 and 0.71 -> 0.61 and 0.32 px (the grey cells' envelope still
    differs from column to column).  Slanted by 0.1 (a tilted board) the lines get no
    long fill: the same bands with it and without.
    """
    rng = np.random.default_rng(11)
    page = _photo_page(0.0, rng)
    short = _photo_bands(page, 13)
    long = _photo_bands(page, 81)
    for p, (length, lines) in enumerate(((15.0, 261), (9.0, 464))):
        assert len(short[p]) < 0.8 * lines
        assert len(long[p]) >= 0.97 * lines
        assert abs(np.median(long[p]) - length) < 0.2
        assert np.percentile(np.abs(long[p] - length), 90) < 0.7
    slanted = _photo_page(0.1, rng)
    for a, b in zip(_photo_bands(slanted, 13), _photo_bands(slanted, 81), strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_frame_after_the_warm_up_compiles_nothing(rig2):
    """:meth:`DepthPipeline.warm_up` compiles (or loads) every kernel a frame reaches, so
    that no frame stalls on numba's compiler: the demo's first frames (two boards before
    a wall: overlapping bands, the arcs' intervals, the second reading, the depth from
    the line intervals) compile nothing more.  Counted with numba's compile events (run
    in a fresh process, this covers every kernel; after other tests, what they left).
    """
    import argparse
    from dataclasses import replace

    from numba.core import event

    from lightflow.app.commands.demo import simulated_crosstalk
    from lightflow.app.options import pipeline_config

    args = argparse.Namespace(stride=STRIDE, smoothing=None, crosstalk=None)
    config = replace(pipeline_config(args), crosstalk="auto")
    with SyntheticCamera(rig2, "boards-wall", frames=2, seed=0) as cam:
        frames = list(cam.frames())
    # the demo's rig: the simulated camera's crosstalk per pattern
    pipe = DepthPipeline(rig2.with_crosstalk(simulated_crosstalk(rig2)), config)
    pipe.warm_up()
    compiled = []

    class Listener(event.Listener):
        def on_start(self, ev) -> None:
            compiled.append(ev.data["dispatcher"].py_func.__qualname__)

        def on_end(self, ev) -> None:
            pass

    listener = Listener()
    event.register("numba:compile", listener)
    try:
        for frame in frames:
            pipe.process(frame)
    finally:
        event.unregister("numba:compile", listener)
    assert compiled == []


def test_boards_whose_bands_touch_are_not_read_an_interval_long(tmp_path):
    """Fresh matrix rig 19 (``lightflow eval --matrix DIR --seeds 19-21``), boards before
    a wall at 30 ms, frame 0: the near board's bands touch (sweep 0.86 of the interval).
    Two rows' floors came from the wall's gaps and read them as a train swept past its
    neighbours (``n = 1``); carried to every row, the near board read 226 mm in front of
    the truth (median; 86 % of the depth on both boards beyond 50 mm).  The touching runs
    measured around them, with two references for ``n``, now overrule such a train
    (:data:`lightflow.app.core.overlap.CONTRADICTION_JUMP`).  Measured on the near board:
    median -0.15 mm, coverage 0.95, 0.2 % beyond 50 mm.  (The far board, mostly too faint
    for bands, is 70 mm off where it gets depth at the image's edge: a known gap.)"""
    from lightflow.app.commands.simulate import simulate_recording
    from lightflow.app.eval_matrix import matrix_cases
    from lightflow.app.recording import load_frame, read_recording

    cases = list(matrix_cases(seeds=(19, 20, 21)))
    n, case = next((n, c) for n, c in enumerate(cases, 1)
                   if c.name == "gen19-boards-wall-30ms")  # fmt: skip
    simulate_recording(case.rig, case.scene, tmp_path / "rec", frames=1,
                       fps=min(10.0, 0.8 / case.exposure_s), exposure_s=case.exposure_s,
                       seed=n)  # fmt: skip
    rec = read_recording(tmp_path / "rec")
    entry = rec.frames[0]
    truth = GroundTruth.load(tmp_path / "rec" / "ground_truth" / f"{entry.stem}.npz")
    pipe = DepthPipeline(rec.rig, PipelineConfig())
    result = pipe.process(Frame(0, entry.t, rec.exposure_s, load_frame(rec, 0), entry.stem))
    ids = [i for i in np.unique(truth.object_id) if i >= 2]
    near = truth.object_id == min(ids, key=lambda i: np.median(truth.depth[truth.object_id == i]))
    has = np.isfinite(result.depth)
    err = (result.depth - truth.depth)[has & near]
    beyond = float(np.mean(np.abs(err) > 0.05))
    lit = near & (truth.lit == 3)
    cover = np.count_nonzero(has & lit) / np.count_nonzero(lit)
    print(f"\nfresh rig 19, boards before a wall, frame 0, near board: median "
          f"{1e3 * np.median(err):+.2f} mm, coverage {cover:.3f}, "
          f"{100 * beyond:.2f} % beyond 50 mm")  # fmt: skip
    assert abs(np.median(err)) <= 0.5e-3
    assert beyond <= 0.01
    assert cover >= 0.85


def test_the_first_frame_compared_with_the_next_gets_the_slow_middle_of_two_balls():
    """Two balls at 5 ms: their slow middles' lines stand still within the exposure but
    move between frames.  The first frame has no frame before it; compared with the next
    one (``process(frame, following)``, as a replay does) it gets them too.

    Measured here (the rig with a projector in front of the camera plane, through a
    crop that holds little more than the balls' middles): coverage 0.010 -> 0.202, median
    58.3 -> 0.24 mm (alone, the few cells with a depth were wrong lines), 1 pixel of depth
    off the balls of 23902.
    """
    rig = _generated_rig(*UNSEEN_RIGS["in front"])
    with SyntheticCamera(rig, "two-balls", frames=2, fps=10, exposure_s=0.005) as cam:
        frames = list(cam.frames())
    truth = frames[0].extras["truth"]
    alone = DepthPipeline(rig, PipelineConfig(stride=STRIDE))
    ahead = DepthPipeline(rig, PipelineConfig(stride=STRIDE))
    first_result = alone.process(frames[0])
    ahead_result = ahead.process(frames[0], frames[1])
    first = scores(rig, truth, first_result, "first frame alone")
    compared = scores(rig, truth, ahead_result, "compared with the next")
    assert first["coverage"] <= 0.05
    assert compared["coverage"] >= 0.17
    assert compared["median_mm"] <= 0.4
    assert compared["off_fraction"] <= 0.001
    # its time counts in the first frame's total
    timings = ahead_result.timings_ms
    assert 0 < timings["next frame"] < timings["total"]
    assert "next frame" not in first_result.timings_ms
    # the next frame was processed and forgotten: the state is the first frame's alone
    assert ahead._frames == alone._frames == 1
    for a, b in ((ahead.flow_model.blur, alone.flow_model.blur), (ahead._leak, alone._leak),
                 (ahead._previous_lines, alone._previous_lines)):
        np.testing.assert_array_equal(a, b)


def test_placing_the_arcs_again_keeps_two_balls_accurate(monkeypatch):
    """``arc_recheck`` (off by default): limb bands whose arcs were placed at a depth the
    frame does not measure at them are placed again and the flows read again.  Here it
    places some again (the second reading runs) and keeps the two balls at 8 ms as
    accurate and at least as complete as without: measured 0.16 mm either way, coverage
    0.617 -> 0.649 on the rig with a projector in front of the camera plane, first frame
    (on the development rigs' distorted two balls it gains up to 12 points:
    docs/history.md)."""
    from lightflow.app.core.arcs import ArcIntervals

    rig = _generated_rig(*UNSEEN_RIGS["in front"])
    with SyntheticCamera(rig, "two-balls", frames=2, fps=10, exposure_s=0.008) as cam:
        frames = list(cam.frames())
    truth = frames[0].extras["truth"]
    placed_again = []
    recheck = ArcIntervals.recheck

    def counting(self, *args):
        again = recheck(self, *args)
        placed_again.append(again is not None)
        return again

    monkeypatch.setattr(ArcIntervals, "recheck", counting)
    found = {}
    for on in (False, True):
        pipeline = DepthPipeline(rig, PipelineConfig(stride=STRIDE, arc_recheck=on))
        found[on] = scores(rig, truth, pipeline.process(frames[0], frames[1]),
                           f"arc_recheck={on}")  # fmt: skip
    assert any(placed_again)
    assert found[True]["median_mm"] <= 0.25
    assert found[True]["coverage"] >= 0.6
    assert found[True]["coverage"] >= found[False]["coverage"] - 0.005
