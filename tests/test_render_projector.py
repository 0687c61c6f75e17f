"""The renderer's projector response: gamma of the patterns' levels and the black level."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from lightflow.app.cli import main
from lightflow.app.core.rig import resolve_rig
from lightflow.drivers.sim.rigspec import read_rig
from lightflow.drivers.sim.scenes import get_scene
from lightflow.drivers.sim.synthetic import (
    SceneRenderer,
    SensorModel,
    pattern_light,
    projector_response,
)

SCALE = 0.08  # 128x96 camera
#: no lens blur, so that every pixel is the renderer's own integral
SHARP = SensorModel(lens_blur_px=0.0)

# The float64 radiance (80x60, t0 = 0.05 s) that the renderer gave before it had a
# projector response (main at 2a01232): its mean and the means of its 10x10-pixel blocks.
# A change of the default physics shows in both; the last bits are not compared, since
# numba compiles the renderer for the host CPU and another CPU rounds differently (a
# byte digest of the ball-wall render, written on one machine, failed on another).
DEFAULT_RENDERS = {
    (r["rig"], r["scene"], r["exact"]): r
    for r in json.loads((Path(__file__).parent / "data" / "default_renders.json").read_text())[
        "renders"
    ]
}


def block_means(rad: np.ndarray, block: int = 10) -> np.ndarray:
    """Means of ``rad``'s ``block`` x ``block`` pixel blocks, per channel."""
    h, w = rad.shape[:2]
    return rad.reshape(h // block, block, w // block, block, -1).mean(axis=(1, 3))


def with_levels(rig, on: dict[int, int], off: dict[int, int] | None = None):
    """The simulator's reading of ``rig`` with pattern m's levels set to ``on[m]``/``off[m]``."""
    spec = read_rig(rig.to_dict())
    off = off or {}
    pats = tuple(
        dataclasses.replace(p, on_level=on.get(m, p.on_level), off_level=off.get(m, p.off_level))
        for m, p in enumerate(spec.patterns)
    )
    return dataclasses.replace(spec, patterns=pats)


@pytest.mark.parametrize("key", sorted(DEFAULT_RENDERS))
def test_default_renders_are_unchanged(key):
    rig_name, scene_name, exact = key
    scene = get_scene(scene_name)
    r = SceneRenderer(resolve_rig(rig_name).scaled(0.05), scene, SensorModel())
    rad = r.radiance(0.05, scene.exposure_s, exact=exact)
    expected = DEFAULT_RENDERS[key]
    assert float(rad.mean()) == pytest.approx(expected["mean"], rel=1e-12)
    np.testing.assert_allclose(block_means(rad), expected["block_means"], rtol=1e-9, atol=0)
    # the defaults are an ideal projector: full light on the lines, none elsewhere
    gain, black = pattern_light(r.spec, SensorModel())
    assert np.array_equal(gain, np.ones(len(r.spec.patterns)))
    assert np.array_equal(black, np.zeros((len(r.spec.projectors), 3)))


def test_projector_response_curve():
    f = projector_response([0, 51, 128, 255], gamma=2.2, black=0.002)
    want = 0.002 + 0.998 * (np.array([0, 51, 128, 255]) / 255.0) ** 2.2
    np.testing.assert_allclose(f, want, rtol=1e-15)
    assert f[0] == 0.002 and f[-1] == 1.0  # contrast 1:500
    # binary levels: the gamma changes nothing
    assert np.array_equal(projector_response([0, 255], gamma=2.2), [0.0, 1.0])
    from lightflow.app.core.errors import ConfigError

    with pytest.raises(ConfigError, match="projector levels: expected 0 .. 255"):
        projector_response([256])
    with pytest.raises(ConfigError, match="projector_black"):
        projector_response([0], black=1.0)


@pytest.mark.parametrize("gamma", [1.0, 2.2])
def test_grey_levels_follow_the_gamma_curve(gamma):
    """Light above the ambient scales as (level / 255) ** gamma, black level or not."""
    rig = resolve_rig("two-projector").scaled(SCALE)
    scene = get_scene("board")
    n_pat = len(read_rig(rig.to_dict()).patterns)
    for black in (0.0, 0.01):
        sensor = dataclasses.replace(SHARP, projector_gamma=gamma, projector_black=black)

        def render(level, sensor=sensor):
            spec = with_levels(rig, dict.fromkeys(range(n_pat), level))
            return SceneRenderer(rig, scene, sensor, spec=spec).radiance(0.1, scene.exposure_s)

        dark, full = render(0), render(255)
        lines = full - dark
        on = lines > 5.0  # DN of line light over the dark pattern (lines reach ~200)
        assert on.mean() > 0.05
        for level in (32, 128, 200):
            ratio = (render(level) - dark)[on] / lines[on]
            np.testing.assert_allclose(ratio, (level / 255) ** gamma, rtol=1e-9)
    # the format's binary patterns look the same whatever the gamma
    plain = SceneRenderer(rig, scene, SHARP).radiance(0.1, scene.exposure_s)
    curved = SceneRenderer(rig, scene, dataclasses.replace(SHARP, projector_gamma=2.2))
    assert np.array_equal(curved.radiance(0.1, scene.exposure_s), plain)


def test_black_level_lights_what_each_projector_lights():
    """A projector showing 0 leaks its black level where it would light, not in its shadow."""
    rig = resolve_rig("two-projector").scaled(SCALE)
    scene = get_scene("ball-wall")  # a ball shadows the wall behind it from each projector
    spec = read_rig(rig.to_dict())
    assert [p.projector for p in spec.patterns] == [0, 1]
    t0, exposure = 0.05, scene.exposure_s
    b = 0.01

    def render(on, off=None, black=0.0):
        sensor = dataclasses.replace(SHARP, projector_black=black)
        r = SceneRenderer(rig, scene, sensor, spec=with_levels(rig, on, off))
        return r, r.radiance(t0, exposure)

    r, ambient = render({0: 0, 1: 0})
    _, leak = render({0: 0, 1: 0}, black=b)
    # each projector alone, all white: its irradiance in its pattern's channel
    irr = []
    for q in (0, 1):
        _, white = render({q: 255, 1 - q: 0}, {q: 255})
        irr.append((white - ambient)[..., spec.patterns[q].channel])
    # both projectors show 0 in all three channels: each leaks b of its light,
    # seen by every camera channel through the crosstalk
    rowsum = np.array(SHARP.crosstalk).sum(axis=1)
    want = b * (irr[0] + irr[1])[..., None] * rowsum
    np.testing.assert_allclose(leak - ambient, want, rtol=1e-9, atol=1e-9)
    # the ground truth's lit bits at the pixel centres, the same at the start, middle
    # and end of the exposure and over the 3x3 neighbours (the pixel's area)
    lit = [r.truth(t0 + f * exposure).lit for f in (0.0, 0.5, 1.0)]
    same = ((lit[0] == lit[1]) & (lit[1] == lit[2])).astype(np.uint8)
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
        same &= (np.roll(lit[1], (dy, dx), (0, 1)) == lit[1]) & (
            np.roll(lit[1], (-dy, -dx), (0, 1)) == lit[1])
    steady = same.astype(bool)
    steady[[0, -1], :] = steady[:, [0, -1]] = False
    for q in (0, 1):
        shadowed = steady & (lit[1] & (1 << q) == 0) & (lit[1] & (1 << (1 - q)) != 0)
        lit_q = steady & (lit[1] & (1 << q) != 0)
        assert shadowed.sum() > 20 and lit_q.sum() > 1000
        # in q's shadow (on the wall, lit by the other one) q leaks nothing (but for
        # a few pixels that a moving shadow edge crosses within the exposure) ...
        assert np.mean(irr[q][shadowed] == 0) > 0.95
        assert irr[q][shadowed].max() < 0.05 * np.median(irr[q][lit_q])
        # ... and where q lights, it leaks b of its light (about 0.4 DN at 1:500)
        assert np.all(irr[q][lit_q] > 10)
    # the leak shows up above the ambient wherever a projector lights
    anywhere = steady & (lit[1] != 0)
    assert np.all((leak - ambient)[anywhere] > 0)
    assert np.all((leak - ambient)[steady & (lit[1] == 0)] <= b * 0.05 * np.median(irr[0]))


def test_simulate_cli_projector_options(tmp_path, capsys):
    out = tmp_path / "rec"
    args = ["simulate", "--rig", "two-projector", "--scene", "board", "--scale", "0.05",
            "--frames", "1", "--out"]  # fmt: skip
    assert main([*args, str(out), "--projector-black", "0.002", "--projector-gamma", "2.2"]) == 0
    sensor = json.loads((out / "ground_truth" / "scene.json").read_text())["sensor"]
    assert sensor["projector_black"] == 0.002 and sensor["projector_gamma"] == 2.2
    capsys.readouterr()
    assert main([*args, str(tmp_path / "bad"), "--projector-black", "0.5"]) == 2
    err = capsys.readouterr().err
    assert err == ("lightflow: error: --projector-black: expected 0 .. 0.1 (a contrast of at "
                   "least 1:10), got 0.5\n")  # fmt: skip
