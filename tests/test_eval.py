"""Accuracy metrics, ``lightflow eval`` on simulated recordings, and the plot helper."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from lightflow.app.cli import main as cli_main
from lightflow.app.commands.simulate import simulate_recording
from lightflow.app.core.rig import resolve_rig
from lightflow.app.evaluation import evaluate_frame, fit_plane, plane_residuals, pool_metrics
from lightflow.app.plot import Series, line_plot, nice_ticks
from lightflow.app.recording import RecordingWriter
from lightflow.drivers.base import Frame
from lightflow.drivers.sim.synthetic import GroundTruth

# ----------------------------------------------------------------------------- metrics


def _truth(depth, object_id, lit, planar=False):
    return GroundTruth(np.asarray(depth, np.float32), np.asarray(object_id, np.uint8),
                       np.asarray(lit, np.uint8), planar)  # fmt: skip


def test_coverage_and_off_object_counting():
    nan = math.nan
    truth = _truth(
        [[1.0, 1.0, 1.0, 1.0], [1.0, 1.0, 2.0, nan]],
        [[2, 2, 2, 2], [3, 1, 1, 0]],
        [[3, 3, 1, 3], [3, 3, 3, 0]],  # pixel (0, 2) is lit by one projector only
    )
    depth = np.array([[1.01, nan, 1.2, 0.97], [1.05, 1.0, nan, 1.5]], np.float32)
    m = evaluate_frame(depth, truth, n_projectors=2)
    # target: moving and lit by both = (0,0), (0,1), (0,3), (1,0); covered: all but (0,1)
    assert (m.n_target, m.n_covered) == (4, 3)
    assert m.coverage == pytest.approx(0.75)
    # depth on 6 pixels, 2 of them off the moving objects (background (1,1), nothing (1,3))
    assert (m.n_depth, m.n_off) == (6, 2)
    assert m.off_object == pytest.approx(2 / 6)
    # errors on moving pixels with depth: 0.01, 0.2 (single-lit still counts), 0.03, 0.05
    assert sorted(np.abs(m.errors).tolist()) == pytest.approx([0.01, 0.03, 0.05, 0.2], abs=1e-6)
    assert m.median_signed_m == pytest.approx(float(np.median(m.errors)), abs=1e-6)
    assert m.median_error_m == pytest.approx(0.04, abs=1e-6)
    assert m.mean_error_m == pytest.approx(0.0725, abs=1e-6)
    assert m.p90_error_m == pytest.approx(0.05 + 0.7 * 0.15, abs=1e-6)
    # 2 cm or more: 0.03, 0.05 and 0.2
    assert m.gross == pytest.approx(0.75)
    assert math.isnan(m.plane_rmse_m)  # not planar
    # without n_projectors, "all projectors" is inferred from the bits present
    assert evaluate_frame(depth, truth).n_target == 4
    # one projector with static depth measures the background too: only (1,3) is off
    m = evaluate_frame(depth, truth, n_projectors=2, background=True)
    assert (m.n_depth, m.n_off, m.n_covered) == (6, 1, 3)


def test_empty_estimate():
    truth = _truth(np.ones((3, 3)), np.full((3, 3), 2), np.full((3, 3), 1), planar=True)
    m = evaluate_frame(np.full((3, 3), np.nan, np.float32), truth, camera_rays_stub(3, 3))
    assert m.coverage == 0.0 and m.off_object == 0.0 and m.n_depth == 0
    assert math.isnan(m.median_error_m) and math.isnan(m.plane_rmse_m) and math.isnan(m.gross)


def camera_rays_stub(h, w, f=100.0):
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.stack([(xs - (w - 1) / 2) / f, (ys - (h - 1) / 2) / f, np.ones((h, w))], -1)


def test_plane_rmse_of_checkerboard_noise_is_exact():
    # a fronto-parallel plane at 0.8 m, depth alternately +-2 mm: the plane z = 0.8
    # is the fit and every point is exactly 2 mm from it
    h, w = 60, 80
    rays = camera_rays_stub(h, w)
    sign = np.where((np.add.outer(np.arange(h), np.arange(w)) % 2) == 0, 1.0, -1.0)
    depth = (0.8 + 0.002 * sign).astype(np.float32)
    truth = _truth(np.full((h, w), 0.8), np.full((h, w), 2), np.full((h, w), 3), planar=True)
    m = evaluate_frame(depth, truth, rays)
    assert m.plane_rmse_m == pytest.approx(0.002, rel=1e-3)
    assert m.median_error_m == pytest.approx(0.002, rel=1e-3)
    assert m.n_plane == h * w and m.coverage == 1.0


def test_plane_fit_tilted_plane_with_noise_and_outliers():
    rng = np.random.default_rng(3)
    n = np.array([0.3, -0.2, -1.0])
    n /= np.linalg.norm(n)
    # plane through (0, 0, 0.75): n . x + d = 0
    d = -n @ np.array([0.0, 0.0, 0.75])
    uv = rng.uniform(-0.3, 0.3, (20000, 2))
    e1 = np.cross(n, [0, 1, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    pts = np.array([0, 0, 0.75]) + uv[:, :1] * e1 + uv[:, 1:] * e2
    noisy = pts + rng.normal(0, 0.003, (len(pts), 1)) * n
    r = plane_residuals(noisy)
    assert np.sqrt(np.mean(r**2)) == pytest.approx(0.003, rel=0.03)
    # 5 % gross outliers 10 cm in front must not tilt the robust plane
    bad = noisy.copy()
    bad[:1000] += 0.1 * n
    normal, offset = fit_plane(bad)
    sign = np.sign(normal @ n)
    assert abs(normal @ n) == pytest.approx(1.0, abs=1e-5)
    assert sign * offset == pytest.approx(d, abs=5e-4)


def test_pooling_weights_pixels():
    a = evaluate_frame(np.full((1, 2), 1.1, np.float32),
                       _truth(np.ones((1, 2)), [[2, 2]], [[1, 1]]))  # fmt: skip
    b = evaluate_frame(np.array([[1.0, np.nan, 1.3, 1.0]], np.float32),
                       _truth(np.ones((1, 4)), [[2, 2, 2, 1]], [[1, 1, 1, 1]]))  # fmt: skip
    pooled = pool_metrics([a, b])
    assert pooled["coverage"] == pytest.approx(4 / 5)  # 2/2 and 2/3
    assert pooled["off_object"] == pytest.approx(1 / 5)
    # errors 0.1, 0.1, 0.0, 0.3 pooled: median 0.1
    assert pooled["median_error_m"] == pytest.approx(0.1, abs=1e-6)
    # 2 cm or more: three of the four
    assert pooled["gross"] == pytest.approx(3 / 4)


def test_nice_ticks():
    assert nice_ticks(2, 40).tolist() == [0, 10, 20, 30, 40]
    assert nice_ticks(0, 3.1).tolist() == [0, 1, 2, 3, 4]
    ticks = nice_ticks(5, 5)
    assert ticks[0] <= 5 <= ticks[-1] and len(ticks) >= 3


def test_line_plot_size_and_content():
    img = line_plot([Series("a", (1, 2, 3), (3, 1, math.nan))], title="t", xlabel="x",
                    ylabel="y", size=(640, 400))  # fmt: skip
    assert img.shape == (400, 640, 3) and img.dtype == np.uint8
    # the series colour appears (drawn line), the background is white
    assert np.any(np.all(img == (178, 114, 0), axis=-1))
    assert (img == 255).mean() > 0.8


# ----------------------------------------------------------------------------- eval CLI


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    """Two board recordings at 0.25 scale, 10 ms and 20 ms exposure.

    The LUT and profile-table cache is the default one, shared with the rest of the
    suite: a private cache would rebuild the profile tables in every run.
    """
    base = tmp_path_factory.mktemp("eval")
    rig = resolve_rig("two-projector").scaled(0.25)
    recs = []
    for exposure in (0.01, 0.02):
        out = base / f"board-{exposure * 1e3:g}ms"
        simulate_recording(rig, "board", out, frames=2, exposure_s=exposure)
        recs.append(out)
    return recs


def test_eval_one_recording(recordings, tmp_path, capsys):
    rec = recordings[1]
    js = tmp_path / "m.json"
    plot = tmp_path / "one.png"
    assert cli_main(["eval", str(rec), "--json", str(js), "--plot", str(plot)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].split()[:3] == ["recording", "scene", "exposure"]
    row = out[2].split()
    assert row[:4] == [str(rec), "board", "20", "2"]
    m = json.loads(js.read_text())["recordings"][0]
    assert m["scene"] == "board" and m["frames"] == 2 and m["planar"] is True
    assert m["exposure_s"] == pytest.approx(0.02)
    # loose: the lead is still tuning the pipeline
    assert m["median_error_m"] < 0.06
    assert m["coverage"] > 0.05
    assert m["off_object"] <= 0.02
    assert 0 < m["plane_rmse_m"] < 0.06
    assert len(m["per_frame"]) == 2 and "errors" not in m["per_frame"][0]
    assert cv2.imread(str(plot)).shape == (560, 900, 3)


def test_eval_two_exposures_draws_plot(recordings, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert cli_main(["eval", *map(str, recordings)]) == 0
    out = capsys.readouterr().out
    assert "plot written to eval.png" in out
    rows = out.splitlines()[2:4]
    assert [r.split()[2] for r in rows] == ["10", "20"]
    png = Path(tmp_path / "eval.png")
    assert png.stat().st_size > 5000
    img = cv2.imread(str(png))
    assert img.shape == (560, 900, 3)
    assert (img != 255).any(axis=-1).mean() > 0.02  # axes, text and lines were drawn


def test_eval_without_ground_truth_is_one_line(tmp_path, capsys):
    rig = resolve_rig("two-projector").scaled(0.05)
    rec = tmp_path / "captured"
    with RecordingWriter(rec, rig, 0.02) as writer:
        writer.write(Frame(0, 0.0, 0.02, np.zeros((60, 80, 3), np.uint8)))
    assert cli_main(["eval", str(rec)]) == 2
    err = capsys.readouterr().err
    assert err == (f"lightflow: error: {rec}: no ground truth (ground_truth/ folder) — eval "
                   "needs a simulated recording\n")  # fmt: skip


def test_matrix_case_filter_names_no_case_in_one_line(tmp_path, capsys):
    assert cli_main(["eval", "--matrix", str(tmp_path / "m"), "--case", "gen2026-ball-*",
                     "--case", "no-such-case"]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert err.startswith("lightflow: error: --case 'no-such-case': no case of the matrix "
                          "matches (names like 'gen2026-board-20ms')") and err.count("\n") == 1
    assert not list((tmp_path / "m").glob("gen*"))  # nothing rendered


def test_matrix_replays_with_the_stride_asked_for(tmp_path, monkeypatch):
    """``--stride`` reaches the matrix's replays (it was ignored there)."""
    import lightflow.app.eval_matrix as em

    seen = {}

    def run_matrix(out, **kw):
        seen.update(kw)
        return []

    monkeypatch.setattr(em, "run_matrix", run_matrix)
    assert cli_main(["eval", "--matrix", str(tmp_path / "m"), "--stride", "8"]) == 0
    assert seen["config"].stride == 8
    assert cli_main(["eval", "--matrix", str(tmp_path / "m")]) == 0
    assert seen["config"] is None  # the pipeline's own


def test_bench_stage_table():
    from lightflow.app.commands.bench import stage_table

    timings = [{"bands": float(i), "flow": 2.0 * i, "total": 3.0 * i} for i in range(1, 11)]
    lines = stage_table(timings, [3.0 * i + 1 for i in range(1, 11)])
    rows = {ln.split("  ")[0].strip(): ln.split()[-2:] for ln in lines[2:] if ln[0] != "-"}
    assert list(rows) == ["bands", "flow", "total", "wall per frame"]
    assert rows["bands"] == ["5.5", "9.1"]  # median and p90 of 1..10
    assert rows["wall per frame"] == ["17.5", "28.3"]


def test_matrix_rigs_span_the_geometry_users_build():
    """Generated rigs: one projector in front of the camera plane, toe-in 15-35 deg,
    pitches 16-40 px, one distorted; tuning and reported seeds never overlap."""
    from lightflow.app.core.geometry import project_points
    from lightflow.app.core.rig import rig_from_dict
    from lightflow.app.eval_matrix import (
        REPORT_SEEDS,
        TUNING_SEEDS,
        cropped,
        generated_rig,
        matrix_cases,
    )

    assert not set(TUNING_SEEDS) & set(REPORT_SEEDS)
    for seed in (*TUNING_SEEDS, *REPORT_SEEDS):
        rig = rig_from_dict(generated_rig(seed, distorted=seed == REPORT_SEEDS[-1]), "gen")
        zs = sorted(float(p.centre_in_camera[2]) for p in rig.projectors)
        assert zs[0] < 0 < zs[1]  # one behind the camera plane, one in front
        for p in rig.projectors:
            toe = math.degrees(math.atan2(abs(p.R[2, 0]), p.R[2, 2]))
            assert 15 <= toe <= 35
            assert 16 <= p.patterns[0].pitch_px <= 40
    cases = list(matrix_cases())
    assert {c.scene for c in cases} >= {"board", "diagonal-board", "newspaper-board", "fan-1ms",
                                        "ball-toward", "ball-away", "two-balls"}  # fmt: skip
    # every scene, but those that only repeat one at another exposure, and the blur
    # calibration's board (rendered for every rig, not scored)
    from lightflow.app.eval_matrix import BLUR_SCENE
    from lightflow.drivers.sim.scenes import SCENES

    repeats = {"fan", "ball", "textured-board"}
    assert {c.scene for c in cases} == set(SCENES) - repeats - {BLUR_SCENE}
    assert any("distorted" in c.rig_name for c in cases)
    assert any(c.rig_name == "single-projector" for c in cases)
    assert {c.exposure_s for c in cases if c.scene == "fan-1ms"} == {0.001}
    assert {c.exposure_s for c in cases if "ball" in c.scene} == {0.005, 0.008}
    assert {c.exposure_s for c in cases if "newspaper" in c.scene} == {0.3}
    assert {c.exposure_s for c in cases if c.scene == "slow-board"} == {0.3}  # the paper's
    # the first rig again with a camera gamma and a defocus disc (unmodelled physics)
    physics = {dict(c.sensor).get("camera_gamma", 1.0) for c in cases if c.sensor}
    assert 2.2 in physics
    assert any(dict(c.sensor).get("lens_psf") == "disk" for c in cases)
    assert all(c.rig_name.startswith(f"gen{REPORT_SEEDS[0]}+") for c in cases if c.sensor)
    # a crop sees a point where the full camera does, shifted by the crop's corner
    full = rig_from_dict(generated_rig(REPORT_SEEDS[-1], distorted=True), "gen")
    crop = cropped(full, (800, 600))
    pts = np.array([[0.05, -0.03, 0.8], [-0.1, 0.07, 0.6]])
    a = project_points(full.camera.K, full.camera.dist, pts)
    b = project_points(crop.camera.K, crop.camera.dist, pts)
    np.testing.assert_allclose(a - b, [[400, 300], [400, 300]], atol=1e-9)


# ----------------------------------------------------------------------------- pictures


def test_error_panel_colours():
    from lightflow.app.pictures import NO_DEPTH_RGB, OFF_OBJECT_RGB, error_rgb

    truth = np.full((1, 6), 0.8, np.float32)
    depth = np.array([[0.8, 0.84, 0.76, np.nan, 0.8, np.nan]], np.float32)
    target = np.array([[1, 1, 1, 1, 0, 0]], bool)
    moving = target.copy()
    rgb = error_rgb(depth, truth, target, moving)
    assert rgb[0, 0].min() > 0.9  # no error: white
    assert rgb[0, 1, 0] > 0.3 > rgb[0, 1, 2]  # 40 mm too far: red
    assert rgb[0, 2, 2] > 0.3 > rgb[0, 2, 0]  # 40 mm too near: blue
    assert tuple(rgb[0, 3]) == pytest.approx(NO_DEPTH_RGB)  # on the object, no depth
    assert tuple(rgb[0, 4]) == pytest.approx(OFF_OBJECT_RGB)  # depth off the object
    assert (rgb[0, 5] == 0).all()  # background


def test_eval_pictures(recordings, tmp_path, capsys):
    rec = recordings[1]
    out = tmp_path / "pics"
    assert cli_main(["eval", str(rec), "--pictures", str(out)]) == 0
    assert f"pictures written to {out}/" in capsys.readouterr().out
    img = cv2.imread(str(out / f"{rec.name}.png"))
    assert img.shape[1] == 1260 and 300 < img.shape[0] < 500  # three panels side by side
    # the causes panel shows the board's depth in its colour (0, 200, 0), BGR here
    green = (np.abs(img.astype(int) - (0, 200, 0)).sum(axis=-1) < 30).mean()
    assert green > 0.05


def test_eval_pictures_folder_that_cannot_be_made_is_one_line(recordings, tmp_path, capsys):
    blocked = tmp_path / "file"
    blocked.write_text("")
    assert cli_main(["eval", str(recordings[0]), "--pictures", str(blocked / "pics")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"lightflow: error: --pictures {blocked / 'pics'}: cannot create")
    assert err.count("\n") == 1


def test_matrix_on_fresh_seeds(tmp_path, capsys):
    """`--seeds` draws the two-projector rigs from other seeds (the last one distorted);
    a malformed list, or one given with --tuning-rigs, is one line and exit status 2."""
    from lightflow.app.commands.eval import _seed_list
    from lightflow.app.eval_matrix import matrix_cases

    assert _seed_list("7-9,12") == (7, 8, 9, 12)
    names = {c.rig_name for c in matrix_cases(seeds=(7, 8))}
    assert {"gen7", "gen8-distorted", "single-projector"} <= names
    assert not any(n.startswith("gen2026") for n in names)
    for bad in (["--seeds", "9-7"], ["--seeds", "x"], ["--seeds", "3-"], ["--seeds", "3-5,4"],
                ["--seeds", "3", "--tuning-rigs"]):  # fmt: skip
        assert cli_main(["eval", "--matrix", str(tmp_path / "m"), *bad]) == 2, bad
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("lightflow: error: --seeds"), err
    assert not (tmp_path / "m").exists()  # nothing created
    assert cli_main(["eval", "--seeds", "3"]) == 2
    assert capsys.readouterr().err == "lightflow: error: --seeds: only with --matrix DIR\n"


def test_matrix_table_shows_the_gross_share_to_a_tenth():
    """The matrix table's columns line up with its header, and the share of depth 2 cm off
    or more shows to a tenth of a per cent (a few tenths are worth seeing there)."""
    from types import SimpleNamespace

    from lightflow.app.eval_matrix import format_matrix

    case = SimpleNamespace(rig_name="gen2026", scene="fan-1ms", exposure_s=0.001)
    m = SimpleNamespace(median_error_m=1e-4, median_signed_m=-1e-4, p90_error_m=0.0052,
                        gross=0.069, coverage=0.75, off_object=0.02, within_1sigma=0.87,
                        within_2sigma=0.9, no_depth_causes={"irregular": 0.1})  # fmt: skip
    head, rule, row = format_matrix([(case, m)])
    cells = [c.strip() for c in row.strip("|").split("|")]
    names = [c.strip() for c in head.replace("\\|", "/").strip("|").split("|")]
    assert len(cells) == len(names) == rule.count("---")
    assert cells[names.index("2 cm off or more")] == "6.9 %"
    assert cells[names.index("coverage")] == "75 %"
