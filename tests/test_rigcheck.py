"""`check_rig`: usable example rigs, degenerate rigs flagged, numbers and pictures."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lightflow.app.core.depth_model import DepthRange, h_function
from lightflow.app.core.errors import ConfigError
from lightflow.app.core.rig import load_rig, rig_from_dict
from lightflow.app.rigcheck import (
    BAND_PX,
    DISPLAY_WIDTH,
    FLAT,
    LEGEND_HEIGHT,
    NOT_INVERTIBLE,
    NOT_LIT,
    SUBPIXEL_PX,
    USABLE,
    check_rig,
)

RIGS = Path(__file__).resolve().parents[1] / "app" / "rigs"
CAM_F = 1800.0


def K(f, w, h):
    return [[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]]


def rot_y(angle):
    c, s = np.cos(angle), np.sin(angle)
    return [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]


def projector(name, f, centre, aim, patterns):
    """A 1280x800 projector at ``centre`` (camera frame) whose axis is turned ``aim`` toward +x."""
    # X_proj = R X_cam + t: the projector's axis in camera coordinates is R[2]
    R = np.array(rot_y(-aim))
    return {
        "name": name, "width": 1280, "height": 800, "K": K(f, 1280, 800), "dist": [0.0] * 5,
        "R": R.tolist(), "t": (-R @ np.asarray(centre, float)).tolist(), "patterns": patterns,
    }  # fmt: skip


def uniform(channel, pitch):
    return {"channel": channel, "kind": "uniform", "pitch_px": pitch, "width_px": 3.0,
            "offset_px": 0.0}  # fmt: skip


def rig(*projectors):
    return rig_from_dict({
        "format": "lightflow-rig/1",
        "camera": {"width": 1600, "height": 1200, "K": K(CAM_F, 1600, 1200), "dist": [0.0] * 5},
        "projectors": list(projectors),
    })  # fmt: skip


PARALLEL = rig(
    projector("left", 1000.0, [-0.2, 0, 0], 0.0, [uniform("red", 32.0)]),
    projector("right", 1500.0, [0.2, 0, 0], 0.0, [uniform("blue", 22.0)]),
)
# converging on (0, 0, 0.75) from either side, 0.6 m apart in depth (the paper's good setup)
GOOD = rig(
    projector("left", 1000.0, [-0.25, 0, 0.25], np.arctan2(0.25, 0.5), [uniform("red", 32.0)]),
    projector("right", 1500.0, [0.3, 0, -0.35], np.arctan2(-0.3, 1.1), [uniform("blue", 22.0)]),
)


def single(centre, kinds=("exp2", "exp2-reversed")):
    pats = [{"channel": c, "kind": k, "lines": 50, "width_px": 3.0}
            for c, k in zip(("red", "blue"), kinds, strict=True)]  # fmt: skip
    aim = np.arctan2(-centre[0], 0.75)  # at the scene centre 0.75 m in front of the camera
    return rig(projector("main", 1500.0, centre, aim, pats))


@pytest.fixture(scope="module")
def example_reports():
    return {
        n: check_rig(load_rig(RIGS / f"{n}.json")) for n in ("two-projector", "single-projector")
    }


@pytest.mark.parametrize("name", ["two-projector", "single-projector"])
def test_example_rigs_are_usable(example_reports, name):
    report = example_reports[name]
    assert report.problem is None and report.usable
    assert report.coverage > 0.5
    at = {st.z: st for st in report.stats}
    # per pixel, before any smoothing, for a 1/4 px band error; the two-projector example
    # trades some slope for flows that stay similar across the view (coverage)
    assert at[0.75].median_error_mm < 45
    assert at[0.75].median_slope > 0.3
    # closer is steeper and more precise (h changes like 1/z)
    assert at[0.5].median_error_mm < at[0.75].median_error_mm < at[1.0].median_error_mm
    lines = report.summary_lines()
    assert all(isinstance(line, str) for line in lines)
    assert any("0.75 m" in line for line in lines) and lines[-1] == "verdict: usable"
    assert all(isinstance(w, str) and w for w in report.warnings)


def test_good_synthetic_rig_is_usable_without_flat_pixels():
    report = check_rig(GOOD)
    assert report.problem is None
    assert report.flat_fraction < 0.05
    assert report.coverage > 0.5
    assert report.stats[1].median_error_mm < 30


@pytest.mark.parametrize(
    "bad, field, cause",
    [
        (PARALLEL, "projectors", "(parallel projectors?)"),
        (single([0.0, 0.0, 0.0]), "projectors[0]", "baseline"),
        (single([0.0, 0.3, 0.0]), "projectors[0]", "baseline"),  # vertical baseline: u fixed
        (single([-0.3, 0.0, 0.0], ("exp2", "exp2")), "projectors[0].patterns", "spacing law"),
    ],
    ids=["parallel", "single-no-baseline", "single-vertical-baseline", "single-same-law"],
)
def test_degenerate_rigs_are_flagged(bad, field, cause):
    report = check_rig(bad)
    assert not report.usable
    assert report.flat_fraction > 0.97
    assert report.coverage == 0.0
    assert report.problem.startswith(f"{field}: h(z) is flat over ")
    assert cause in report.problem and "no depth can be measured" in report.problem
    assert report.warnings  # what to change
    assert np.all(report.slope[report.classes != NOT_LIT] < 1e-6)


def test_parallel_advice_names_the_move():
    (advice,) = check_rig(PARALLEL).warnings
    assert "nearly parallel" in advice and "forward or backward" in advice


def test_interval_is_pitch_times_focal_ratio_for_a_parallel_pinhole():
    # R = I, fronto-parallel: u = fp (x z + b) / z + c, so one camera pixel moves u by fp/fc
    report = check_rig(PARALLEL, depths=(0.75,))
    lit = report.classes[0] != NOT_LIT
    np.testing.assert_allclose(report.interval_px[0, 0][lit], 32.0 * CAM_F / 1000.0, rtol=1e-6)
    np.testing.assert_allclose(report.interval_px[0, 1][lit], 22.0 * CAM_F / 1500.0, rtol=1e-6)


def test_expected_error_follows_the_quarter_pixel_model():
    report = check_rig(GOOD, depths=(0.75,))
    usable = report.classes[0] == USABLE
    B = report.interval_px[0][:, usable]
    per_flow = SUBPIXEL_PX / BAND_PX + SUBPIXEL_PX / B
    expected = np.sqrt((per_flow**2).sum(axis=0)) / report.slope[0][usable]
    np.testing.assert_allclose(report.error_m[0][usable], expected, rtol=1e-9)
    assert np.all(np.isnan(report.error_m[0][~usable]))
    # the paper's case: dr = 10, B = 30 gives about 0.049 in the log ratio
    assert np.hypot(*(2 * [0.25 / 10 + 0.25 / 30])) == pytest.approx(0.049, abs=0.003)


def test_single_projector_error_counts_only_the_intervals(example_reports):
    report = example_reports["single-projector"]
    usable = report.classes[1] == USABLE
    B = report.interval_px[1][:, usable]
    expected = np.hypot(*(SUBPIXEL_PX / B)) / report.slope[1][usable]
    np.testing.assert_allclose(report.error_m[1][usable], expected, rtol=1e-9)


def test_slope_is_the_derivative_of_h(example_reports):
    rig_ = load_rig(RIGS / "two-projector.json")
    report = check_rig(rig_, depths=(0.75,), stride=200)
    xy = np.array([[0.0, 0.0], [0.1, -0.05]])
    h = [h_function(rig_, xy, np.full(2, z)) for z in (0.74, 0.76)]
    slope = np.abs(h[1] - h[0]) / 0.02
    # grid cell (row 3, column 4) is centred on pixel (4 * 200 + 99.5, 3 * 200 + 99.5)
    cx, cy = rig_.camera.K[0, 2], rig_.camera.K[1, 2]
    fx = rig_.camera.K[0, 0]
    xy_grid = np.array([[(899.5 - cx) / fx, (699.5 - cy) / fx]])
    expected = (
        np.abs(
            h_function(rig_, xy_grid, np.array([0.7501]))
            - h_function(rig_, xy_grid, np.array([0.7499]))
        )
        / 2e-4
    )
    assert report.slope[0, 3, 4] == pytest.approx(expected[0], rel=1e-4)
    assert slope[0] == pytest.approx(report.slope[0, 3, 4], rel=0.05)


def test_depth_outside_the_inverted_range_is_not_invertible():
    report = check_rig(GOOD, depths=(0.75,), depth_range=DepthRange(1.0, 3.0))
    lit = report.classes[0] != NOT_LIT
    assert lit.any()
    assert np.all(report.classes[0][lit] == NOT_INVERTIBLE)
    assert report.problem.startswith("projectors: depth is measurable on only 0.0 %")


def test_classes_partition_the_lit_pixels(example_reports):
    report = example_reports["two-projector"]
    for i, st in enumerate(report.stats):
        n = report.classes[i].size
        assert st.lit == pytest.approx(np.mean(report.lit_by[i].all(axis=0)))
        assert st.usable + st.flat + st.not_invertible == pytest.approx(st.lit)
        assert st.usable == pytest.approx(np.count_nonzero(report.classes[i] == USABLE) / n)
        assert st.flat == pytest.approx(np.count_nonzero(report.classes[i] == FLAT) / n)
    assert report.overlap == pytest.approx(np.mean([st.lit for st in report.stats]))


def test_images_have_the_expected_shapes(example_reports):
    for report in example_reports.values():
        gh, gw = report.classes.shape[1:]
        assert (gh, gw) == (150, 200)  # 1600x1200 camera, stride 8
        height = round(gh * DISPLAY_WIDTH / gw) + LEGEND_HEIGHT
        expected = {f"{kind}-{z:.2f}m" for z in report.depths
                    for kind in ("slope", "error", "usable", "overlap")}  # fmt: skip
        assert set(report.images) == expected
        for img in report.images.values():
            assert img.shape == (height, DISPLAY_WIDTH, 3) and img.dtype == np.uint8
            assert img[:-LEGEND_HEIGHT].std() > 0 or img[-LEGEND_HEIGHT:].min() == 0
        # the usable map is green where depth is measurable
        usable = report.images["usable-0.75m"][: height - LEGEND_HEIGHT]
        green = np.all(usable == (80, 180, 60), axis=-1).mean()
        assert green == pytest.approx(report.stats[1].usable, abs=0.02)


def test_bad_arguments():
    with pytest.raises(ConfigError, match="depths"):
        check_rig(GOOD, depths=())
    with pytest.raises(ConfigError, match="depths"):
        check_rig(GOOD, depths=(-1.0,))
