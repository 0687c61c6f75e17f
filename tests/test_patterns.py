"""Pattern geometry exactly as formats.md defines it, and `lightflow patterns`."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from lightflow.app.cli import main as cli_main
from lightflow.app.core.patterns import (
    line_centres,
    line_index,
    lit_columns,
    local_pitch,
    pattern_image,
)
from lightflow.app.core.rig import Pattern, load_rig

RIGS = Path(__file__).resolve().parents[1] / "app" / "rigs"


def uniform(pitch, width=3.0, offset=0.0):
    return Pattern("red", "uniform", width, pitch_px=pitch, offset_px=offset)


def test_uniform_centres_offset_pitch_and_range():
    np.testing.assert_array_equal(line_centres(uniform(24.0, offset=5.0), 100), [5, 29, 53, 77])
    # u_k = W is outside 0 <= u_k < W, u_k just below W is inside
    np.testing.assert_array_equal(line_centres(uniform(24.0, offset=4.0), 100), [4, 28, 52, 76])
    np.testing.assert_allclose(
        line_centres(uniform(24.0, offset=3.5), 100), [3.5, 27.5, 51.5, 75.5, 99.5]
    )
    centres = line_centres(uniform(32.0), 1280)
    assert len(centres) == 40
    assert centres[0] == 0.0 and centres[-1] == 1248.0


@pytest.mark.parametrize("W, N", [(1280, 50), (1024, 7), (800, 3)])
def test_exp2_centres_follow_formats_md(W, N):
    exp2 = line_centres(Pattern("red", "exp2", 1.0, lines=N), W)
    rev = line_centres(Pattern("blue", "exp2-reversed", 1.0, lines=N), W)
    np.testing.assert_allclose(exp2, [W * (2 ** (k / N) - 1) for k in range(N)], rtol=0, atol=1e-9)
    np.testing.assert_allclose(
        rev, [W * (2 - 2 ** (1 - k / N)) for k in range(1, N + 1)], rtol=0, atol=1e-9
    )
    assert exp2[0] == 0.0 and rev[-1] == W
    # exp2's pitch grows from left to right, exp2-reversed's shrinks
    assert np.all(np.diff(exp2, 2) > 0) and np.all(np.diff(rev, 2) < 0)
    # mirror images of each other: u_rev(k) = W - u_exp2(N - k)
    np.testing.assert_allclose(rev, W - exp2[::-1], atol=1e-9)


@pytest.mark.parametrize(
    "pattern, W",
    [
        (uniform(24.0, width=3.0, offset=5.0), 100),
        (uniform(10.0, width=2.0, offset=0.0), 64),  # |x - u| = 1 exactly is lit
        (uniform(17.0, width=4.5, offset=2.25), 200),
        (Pattern("green", "exp2", 3.0, lines=50), 1280),
        (Pattern("blue", "exp2-reversed", 3.0, lines=50), 1280),
    ],
)
def test_lit_columns_are_within_half_width_of_a_centre(pattern, W):
    lit = lit_columns(pattern, W)
    x = np.arange(W)
    dist = np.abs(x[:, None] - line_centres(pattern, W)[None, :]).min(axis=1)
    np.testing.assert_array_equal(lit, dist <= pattern.width_px / 2)
    assert lit.any() and not lit.all()


def test_even_width_lights_three_columns_around_an_integer_centre():
    lit = lit_columns(uniform(10.0, width=2.0), 30)
    np.testing.assert_array_equal(np.flatnonzero(lit), [0, 1, 9, 10, 11, 19, 20, 21])


@pytest.mark.parametrize(
    "pattern, first_k",
    [
        (uniform(24.0, offset=5.0), 0),
        (Pattern("red", "exp2", 3.0, lines=50), 0),
        (Pattern("blue", "exp2-reversed", 3.0, lines=50), 1),
    ],
)
def test_line_index_is_the_integer_k_at_the_centres(pattern, first_k):
    W = 1280
    centres = line_centres(pattern, W)
    k = line_index(pattern, W, centres)
    np.testing.assert_allclose(k, np.arange(first_k, first_k + len(centres)), atol=1e-9)
    # and continuous and increasing in between
    mid = line_index(pattern, W, (centres[:-1] + centres[1:]) / 2)
    assert np.all((mid > k[:-1]) & (mid < k[1:]))


@pytest.mark.parametrize("kind", ["exp2", "exp2-reversed"])
def test_local_pitch_is_the_symmetric_difference_at_interior_lines(kind):
    W = 1280
    pat = Pattern("red", kind, 3.0, lines=50)
    u = line_centres(pat, W)
    np.testing.assert_allclose(
        local_pitch(pat, W, u[1:-1]), (u[2:] - u[:-2]) / 2, rtol=1e-12, atol=1e-9
    )


def test_local_pitch_of_uniform_is_the_pitch():
    np.testing.assert_array_equal(local_pitch(uniform(24.0), 100, [0.0, 50.0]), [24.0, 24.0])


@pytest.mark.parametrize("rig_name", ["two-projector", "single-projector"])
def test_patterns_command_writes_pattern_image_as_rgb_png(rig_name, tmp_path, capsys):
    rig_file = RIGS / f"{rig_name}.json"
    out = tmp_path / "patterns"
    assert cli_main(["patterns", str(rig_file), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    rig = load_rig(rig_file)
    assert sorted(p.name for p in out.iterdir()) == sorted(f"{p.name}.png" for p in rig.projectors)
    for proj in rig.projectors:
        path = out / f"{proj.name}.png"
        assert str(path) in printed
        expected = pattern_image(proj)
        assert expected.shape == (proj.height, proj.width, 3)
        # PIL reads RGB, OpenCV BGR: both must give back the RGB pattern image
        np.testing.assert_array_equal(np.asarray(Image.open(path).convert("RGB")), expected)
        np.testing.assert_array_equal(cv2.imread(str(path))[..., ::-1], expected)
        for pat in proj.patterns:
            channel = {"red": 0, "green": 1, "blue": 2}[pat.channel]
            np.testing.assert_array_equal(
                expected[0, :, channel] == 255, lit_columns(pat, proj.width)
            )


def test_patterns_command_bad_rig_is_one_line_exit_2(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "lightflow-rig/1"}')
    assert cli_main(["patterns", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(bad) in err and "Traceback" not in err
