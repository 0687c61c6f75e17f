"""Band detector on exactly rendered band profiles, and the colour-leak estimate."""

from __future__ import annotations

import numpy as np
import pytest

from lightflow.app.core.bands import (
    BAND_CUT,
    BAND_FAINT,
    BAND_IRREGULAR,
    BAND_LIMB,
    BAND_STEEP,
    F_CENTRE,
    F_HEIGHT,
    F_INTERVAL,
    F_LENGTH,
    F_RAMP,
    F_SLANT,
    F_VALID,
    N_FIELDS,
    BandParams,
    detect_bands,
    estimate_leak,
    fill_print,
    histogram_median,
    upright_tiles,
)
from lightflow.app.core.profile_model import fit_blur, pixel_value, tables

_B = BandParams()
# the detector's defaults
PARAMS = np.array([_B.min_contrast, _B.interval_tolerance, _B.symmetry_tolerance_px,
                   _B.min_gap_px, _B.vertical_extra], dtype=np.float64)  # fmt: skip
WEIGHTS = np.array([[1.0, 0.0, 0.0]])
#: no edge model: the erf tails of a detector that knows neither line width nor blur
NO_EDGE = np.zeros((1, 3))
AMP = 80.0
BG = 10.0
MAX_BANDS = 96
FIRST = 30.0  # centre of the first band


def band_row(n, centres, L, w, sigma, amp=AMP, bg=BG):
    """One image row: background plus pixel-integrated bands centred at ``centres``."""
    v = np.full(n, bg)
    reach = int(0.5 * (L + w) + 6 * sigma + 3)
    for c in centres:
        for j in range(max(0, int(c) - reach), min(n, int(c) + reach + 2)):
            v[j] += amp * pixel_value(j - c, L, w, sigma)
    return v


def centres_for(interval, count, phase=0.0):
    return FIRST + phase + interval * np.arange(count)


def detect_rows(rows, interval):
    """Run the detector on each row of ``rows`` (R, W); per row, its bands (n, N_FIELDS)."""
    rows = np.atleast_2d(rows)
    img = np.ascontiguousarray(np.repeat(rows[:, :, None], 3, axis=2), dtype=np.float64)
    n_rows = rows.shape[0]
    bands = np.empty((1, n_rows, MAX_BANDS, N_FIELDS))
    counts = np.empty((1, n_rows), np.int64)
    wins = np.array([int(2 * interval) | 1], np.int64)
    row_y = np.arange(n_rows, dtype=np.int64)
    detect_bands(img, WEIGHTS, row_y, wins, 255.0, PARAMS, NO_EDGE, bands, counts)
    return [bands[0, r, : counts[0, r]].copy() for r in range(n_rows)]


def detect_row(v, interval, edge=NO_EDGE):
    """The brief's layout: a (3, W, 3) float image holding the same row three times."""
    img = np.ascontiguousarray(np.repeat(np.repeat(v[None, :, None], 3, 0), 3, 2))
    bands = np.empty((1, 1, MAX_BANDS, N_FIELDS))
    counts = np.empty((1, 1), np.int64)
    detect_bands(img, WEIGHTS, np.array([1], np.int64), np.array([int(2 * interval) | 1], np.int64),
                 255.0, PARAMS, edge, bands, counts)  # fmt: skip
    return bands[0, 0, : counts[0, 0]].copy()


def render_and_detect(L, w, sigma, interval, phase, count=8):
    """Bands of one rendered row, one per rendered line, in order.

    Any further segment the detector reports (a ripple of the flat background)
    must be marked invalid.
    """
    c = centres_for(interval, count, phase)
    v = band_row(int(c[-1] + 40), c, L, w, sigma)
    b = detect_row(v, interval)
    centre = b[:, F_CENTRE]
    match = [np.flatnonzero(np.abs(centre - ck) < 0.25 * interval) for ck in c]
    assert all(len(m) == 1 for m in match), f"lines at {c} -> bands at {centre}"
    idx = np.concatenate(match)
    extra = np.setdiff1d(np.arange(len(b)), idx)
    assert np.all(b[extra, F_VALID] <= 0.0)
    b = b[idx]
    assert np.allclose(b[:, F_CENTRE], c, atol=0.05)
    return b


def gap_for(L, w, sigma):
    """Interval with a clean background gap (as the profile tables are built)."""
    return L + 3 * w + 8 * sigma + 10


# ------------------------------------------------------------------ width at half height


LONG = [  # (L, w, sigma): L >= 2 w + 8 sigma (worst case over 20 phases in the comment)
    (20.0, 3.0, 1.0),  # 0.000
    (12.5, 1.5, 0.6),  # 0.044: sharp ramps, linear interpolation between samples
    (17.5, 2.0, 0.8),  # 0.026
    (21.3, 3.0, 1.0),  # 0.013
    (24.0, 5.0, 1.2),  # 0.004
    (30.0, 6.0, 1.4),  # 0.021
    (28.0, 7.0, 0.6),  # 0.005
    (18.0, 1.5, 1.6),  # 0.002
]


@pytest.mark.parametrize("L,w,sigma", LONG)
def test_long_band_width_equals_sweep(L, w, sigma):
    worst = 0.0
    for phase in (0.0, 0.13, 0.37, 0.5, 0.71, 0.93):
        B = gap_for(L, w, sigma) + 0.29  # non-integer: every band has its own phase
        b = render_and_detect(L, w, sigma, B, phase)
        assert np.all(b[:, F_VALID] == 1.0)
        worst = max(worst, np.max(np.abs(b[:, F_LENGTH] - L)))
        assert np.all(np.abs(b[1:-1, F_INTERVAL] - B) <= 0.05)
    print(f"\nL={L} w={w} sigma={sigma}: max |m - L| = {worst:.4f} px")
    assert worst <= 0.05


# L just above w + 5 sigma: measured m overshoots by up to 0.3 px
JUST_LONG = [(10.5, 7.0, 0.6), (9.5, 6.0, 0.6), (14.0, 7.0, 0.8), (8.0, 1.5, 1.2), (10.5, 5.0, 1.0)]


@pytest.mark.xfail(
    strict=True,
    reason="bands.py: the plateau is the mean over the central half of the band; for "
    "w + 5 sigma < L < ~2 w + 8 sigma that window reaches the rounded shoulders, the height is "
    "underestimated and m overshoots L by up to 0.3 px (e.g. L=10.5, w=7, sigma=0.6: +0.22 px "
    "mean, +0.32 px worst phase)",
)
def test_width_equals_sweep_for_all_bands_longer_than_line_plus_5_sigma():
    errs = []
    for L, w, sigma in JUST_LONG:
        assert L > w + 5 * sigma
        for phase in np.arange(8) / 8:
            b = render_and_detect(L, w, sigma, gap_for(L, w, sigma), phase)
            errs.append((np.max(np.abs(b[:, F_LENGTH] - L)), L, w, sigma, phase))
    worst = max(errs)
    print(f"\nworst |m - L| = {worst[0]:.3f} px at L={worst[1]} w={worst[2]} sigma={worst[3]}")
    assert worst[0] <= 0.05


# ------------------------------------------------------------------ sweep from m


def test_true_length_recovers_sweep():
    """4 <= L <= 30, w in [1.5, 7], sigma in [0.6, 1.6]; here only L >= 6 and L >= w + 5 sigma."""
    rng = np.random.default_rng(21)
    t = tables()
    worst = (0.0,)
    n_cases = 0
    while n_cases < 40:
        L = rng.uniform(4.0, 30.0)
        w = rng.uniform(1.5, 7.0)
        sigma = rng.uniform(0.6, 1.6)
        if L < 6.0 or L < w + 5 * sigma:
            continue
        n_cases += 1
        B = gap_for(L, w, sigma) + rng.uniform(0.0, 6.0)
        b = render_and_detect(L, w, sigma, B, rng.uniform())
        assert np.all(b[:, F_VALID] == 1.0)
        rec = t.true_length(b[:, F_LENGTH], w, sigma)
        rel = np.abs(rec - L) / L
        assert np.all(np.isfinite(rel))
        worst = max(worst, (rel.max(), L, w, sigma))
    print(f"\ntrue_length: worst relative error {100 * worst[0]:.2f} % "
          f"(L={worst[1]:.2f}, w={worst[2]:.2f}, sigma={worst[3]:.2f})")  # fmt: skip
    assert worst[0] <= 0.015


# short bands that still count as moving (L > 0.6 w + 1) and have an invertible m(L)
SHORT = [(4.0, 3.0, 1.6), (4.0, 2.0, 1.6), (5.0, 4.0, 1.4), (4.0, 3.0, 0.6), (4.5, 3.0, 1.6)]


@pytest.mark.xfail(
    strict=True,
    reason="bands.py: for short bands the plateau window [ceil(xl + m/4), floor(xr - m/4)] "
    "holds 0 or 1 whole pixels, so the height (and m) jumps with the sub-pixel phase by ~0.2 px; "
    "the tables average 4 phases, so single bands are off by up to 7 % (L=4, w=3, sigma=1.6)",
)
def test_true_length_recovers_short_sweeps_at_every_phase():
    t = tables()
    errs = []
    for L, w, sigma in SHORT:
        for phase in np.arange(8) / 8:
            b = render_and_detect(L, w, sigma, gap_for(L, w, sigma), phase)
            rec = t.true_length(b[1:-1, F_LENGTH], w, sigma)
            errs.append((float(np.max(np.abs(rec - L) / L)), L, w, sigma, phase))
    worst = max(errs)
    print(f"\nshort bands: worst {100 * worst[0]:.1f} % at L={worst[1]} w={worst[2]} "
          f"sigma={worst[3]} phase={worst[4]}")  # fmt: skip
    assert worst[0] <= 0.015


# ------------------------------------------------------------------ interval


@pytest.mark.parametrize(
    "L,w,sigma,B",
    [
        (6.0, 3.0, 1.0, 17.3),
        (10.0, 2.0, 0.8, 23.85),
        (20.0, 3.0, 1.2, 40.1),
        (30.0, 5.0, 1.0, 61.7),
    ],
)
def test_interval_equals_line_spacing(L, w, sigma, B):
    for phase in (0.0, 0.4, 0.8):
        b = render_and_detect(L, w, sigma, B, phase, count=10)
        inner = b[1:-1]
        assert np.all(inner[:, F_VALID] == 1.0)
        err = np.abs(inner[:, F_INTERVAL] - B)
        assert err.max() <= 0.05, err.max()
        # the outermost bands extrapolate their interval from one side
        assert np.all(np.abs(b[[0, -1], F_INTERVAL] - B) <= 0.05)


# ------------------------------------------------------------------ rejections


_TOUCHING = pytest.mark.xfail(
    strict=True,
    reason="bands.py: with erf tails, bands that just touch (L + w = B, w=5, sigma=1.4) leave a "
    "V-shaped notch a few samples wide, too short for the V test of the gaps; measured against its "
    "raised level the band reads m=13.7 for L=15 and stays valid.  A V test on short gaps that "
    "rejects it also rejects real bands 2-3 px apart (gen1 board at 20 ms: 40 % of the frame).  "
    "With the line width and blur known, the tails bring the background down to the floor, the "
    "band's 20 % crossings lie past the gaps' middles, and it is rejected",
)


def _overlap_cases(cases):
    """Each case with erf tails and with the edge model known (the touching case's known
    failure is the erf tails')."""
    out = []
    for B, w, sigma, over in cases:
        for known in (False, True):
            touching = not known and (B, w, sigma, over) == (20.0, 5.0, 1.4, 0.0)
            tails = "known-edge" if known else "erf-tails"
            name = f"{tails}-B{B:g}-w{w:g}-s{sigma:g}-over{over:+g}"
            out.append(pytest.param(B, w, sigma, over, known,
                                    marks=(_TOUCHING,) if touching else (), id=name))  # fmt: skip
    return out


@pytest.mark.parametrize(
    "B,w,sigma,over,known",  # over = L + w - B
    _overlap_cases([
        # (these three: the tails of touching bands, subtracted from the gap level, no longer
        # hide the overlap; overlapping ramps and the pulses of bands longer than the
        # interval lie on a floor raised above the gaps outside the overlap)
        (30.0, 3.0, 1.0, -1.0),
        (30.0, 3.0, 1.0, 0.0),
        (30.0, 3.0, 1.0, 2.0),
        (30.0, 3.0, 1.0, 3.0),
        (30.0, 3.0, 1.0, 5.0),
        (20.0, 5.0, 1.4, 0.0),
        (20.0, 5.0, 1.4, 3.0),
        (20.0, 5.0, 1.4, 5.0),
        (20.0, 2.0, 0.7, 5.0),
    ]),
)  # fmt: skip
def test_overlapping_bands_are_invalid(B, w, sigma, over, known):
    L = B - w + over
    c = centres_for(B, 12, 0.3)
    v = band_row(int(c[-1] + 40), c, L, w, sigma)
    b = detect_row(v, B, known_edge(B, w, sigma) if known else NO_EDGE)
    valid = b[:, F_VALID] == 1.0
    print(f"\nL={L:g} w={w:g} B={B:g}: {len(b)} bands, {valid.sum()} valid, "
          f"m of valid {np.round(b[valid, F_LENGTH], 2)[:4]}")  # fmt: skip
    if known and over < 0:
        # supports 1 px apart do not overlap: with the tails subtracted exactly, measured
        assert valid.all() and np.all(np.abs(b[:, F_LENGTH] / L - 1.0) < 0.003)
        return
    assert not valid.any()


LONGER_THAN_INTERVAL = [(20.0, 2.0, 0.7), (20.0, 5.0, 1.4), (30.0, 3.0, 1.0), (40.0, 7.0, 0.6),
                        (25.0, 3.0, 1.6), (16.0, 2.0, 0.8)]  # fmt: skip


@pytest.mark.parametrize("known", [False, True], ids=["erf-tails", "known-edge"])
@pytest.mark.parametrize("B,w,sigma", LONGER_THAN_INTERVAL)
def test_bands_longer_than_the_interval_are_never_valid(B, w, sigma, known):
    """Swept lines longer than their interval leave pulses on a raised floor: never valid.

    The pulses look like short bands with clean gaps; the floor outside the overlap (here
    30 px of background at both ends of the row) tells them apart.
    """
    valid = 0
    for r in np.arange(1.0, 2.55, 0.05):
        L = r * B
        for phase in (0.0, 0.3, 0.6):
            c = 0.5 * (L + w) + 30.0 + phase + (B + 0.17) * np.arange(14)
            v = band_row(int(c[-1] + 0.5 * (L + w) + 30), c, L, w, sigma)
            edge = known_edge(B, w, sigma) if known else NO_EDGE
            valid += int(np.sum(detect_row(v, B, edge)[:, F_VALID] == 1.0))
    assert valid == 0


@pytest.mark.parametrize("known", [False, True], ids=["erf-tails", "known-edge"])
def test_a_band_at_the_image_border_is_cut_not_touching(known):
    """The gap at a row's end is cut short by the border: a band a few pixels inside it
    is cut (no centre, so no neighbour's interval and no periodic run), never a band
    that touches a neighbour."""
    B, L, w, sigma = 24.0, 12.0, 3.0, 1.0
    for first in (7.0, 8.0, 9.0, 10.0):
        c = first + B * np.arange(6)
        v = band_row(int(c[-1] + 40), c, L, w, sigma)
        b = detect_row(v, B, known_edge(B, w, sigma) if known else NO_EDGE)
        assert b[0, F_VALID] in (BAND_CUT, BAND_FAINT), first
        assert np.isnan(b[0, F_CENTRE]), first
        assert np.all(b[1:5, F_VALID] == 1.0), first


def known_edge(B, w, sigma):
    """The detector's edge model of lines ``w`` px wide, ``B`` px apart, blurred by
    ``sigma`` (FlowModel.edge_model's form: one pitch, a blur that does not scale)."""
    return np.array([[w / B, sigma * sigma, 0.0]])


@pytest.mark.parametrize(
    "B,L,w,sigma",  # gap between the lines' supports B - L - w: 2.2 to 5.3 px, 2.5 to 6 sigma
    [(24.3, 18.5, 3.6, 0.92), (24.3, 17.0, 3.6, 0.92), (16.4, 11.5, 2.4, 0.85),
     (16.4, 10.5, 2.4, 0.85), (31.6, 22.0, 4.3, 0.9), (31.6, 26.4, 2.0, 0.9)],
)  # fmt: skip
def test_bands_with_narrow_gaps_read_their_width_with_the_line_width_and_blur_known(B, L, w,
                                                                                   sigma):
    """The tails of touching bands raise their gaps; knowing the line width and the blur,
    the detector subtracts them exactly, and every band reads its width at half height
    within 0.25 % (the erf tails of the measured ramps read up to 1 % short here)."""
    c = centres_for(B, 30, 0.3)
    v = band_row(int(c[-1] + 40), c, L, w, sigma)
    errors = {}
    for name, edge in (("erf", NO_EDGE), ("known", known_edge(B, w, sigma))):
        b = detect_row(v, B, edge)
        valid = b[b[:, F_VALID] == 1.0]
        assert len(valid) >= 28  # the outermost two may have no one-sided interval
        errors[name] = valid[:, F_LENGTH] / L - 1.0
    print(f"\nB={B} L={L}: erf {100 * np.median(errors['erf']):+.2f} %, "
          f"known {100 * np.median(errors['known']):+.2f} %")  # fmt: skip
    assert np.all(np.abs(errors["known"]) < 0.0025)


def test_bands_with_a_clean_gap_next_to_the_overlap_cases_are_valid():
    """Sanity check of the overlap setup: the same lines with a flat gap are all measured."""
    for B, w, sigma, L in [(30.0, 3.0, 1.0, 17.0), (20.0, 2.0, 0.7, 10.0), (30.0, 5.0, 1.4, 11.0)]:
        assert L + w + 8 * sigma + 2 <= B
        b = render_and_detect(L, w, sigma, B, 0.3, count=12)
        assert np.all(b[:, F_VALID] == 1.0)


@pytest.mark.parametrize(
    "cut",
    [
        pytest.param(-0.3, id="cut-before-centre"),
        pytest.param(0.1, id="cut-just-past-centre"),
        pytest.param(0.25, id="cut-at-three-quarters"),
        pytest.param(0.4, id="cut-near-end"),
    ],
)
def test_band_cut_by_hard_edge_is_invalid(cut):
    L, w, sigma, B = 20.0, 3.0, 1.0, 40.0
    c = centres_for(B, 10, 0.3)
    v = band_row(int(c[-1] + 40), c, L, w, sigma)
    k = 6
    x_cut = int(c[k] + cut * L)
    v[x_cut:] = BG
    b = detect_row(v, B)
    # the far neighbours are untouched
    far = b[np.abs(b[:, F_CENTRE] - c[k]) > 1.5 * B]
    assert len(far) == k - 1
    assert np.all(far[:, F_VALID] == 1.0)
    assert np.all(np.abs(far[:, F_LENGTH] - L) <= 0.05)
    cut_band = b[np.nanargmax(b[:, F_CENTRE])]
    assert abs(cut_band[F_CENTRE] - c[k]) < L / 2
    print(f"\ncut at centre{cut * L:+.0f} px: cut band m={cut_band[F_LENGTH]:.2f} "
          f"valid={cut_band[F_VALID]:.0f}")  # fmt: skip
    assert cut_band[F_VALID] <= 0.0


def test_band_with_dip_in_plateau_is_invalid():
    L, w, sigma, B = 20.0, 3.0, 1.0, 40.0
    c = centres_for(B, 10, 0.3)
    v = band_row(int(c[-1] + 40), c, L, w, sigma)
    k = 5
    j = int(c[k])
    v[j - 1 : j + 2] *= 0.3  # a stroke of print across the band
    b = detect_row(v, B)
    near = np.abs(b[:, F_CENTRE] - c[k]) < L / 2
    assert near.any()
    assert np.all(b[near, F_VALID] <= 0.0)
    far = np.abs(b[:, F_CENTRE] - c[k]) > 1.5 * B
    assert far.sum() == len(c) - 3
    assert np.all(b[far, F_VALID] == 1.0)
    assert np.all(np.abs(b[far, F_LENGTH] - L) <= 0.05)


def test_noise_leaves_median_width_unbiased():
    L, w, sigma, B = 14.0, 3.0, 1.0, 37.3
    c = centres_for(B, 26, 0.3)
    v = band_row(int(c[-1] + 40), c, L, w, sigma)
    clean = detect_rows(v, B)[0]
    m_clean = np.median(clean[clean[:, F_VALID] == 1.0, F_LENGTH])
    rng = np.random.default_rng(3)
    noisy = v[None, :] + rng.normal(0.0, 1.5, (40, v.size))
    per_row = detect_rows(noisy, B)
    allb = np.concatenate(per_row)
    valid = allb[allb[:, F_VALID] == 1.0]
    m_noisy = np.median(valid[:, F_LENGTH])
    print(f"\nnoise 1.5 DN on {AMP:g}: {len(valid)}/{len(allb)} bands valid, median m "
          f"{m_noisy:.3f} vs {m_clean:.3f} noise-free (L={L:g}), "
          f"sd {np.std(valid[:, F_LENGTH]):.3f}")  # fmt: skip
    assert len(valid) >= 0.9 * 40 * len(c)
    assert abs(m_noisy - m_clean) <= 0.1
    assert abs(np.median(valid[:, F_INTERVAL]) - B) <= 0.05


# ------------------------------------------------------------------ colour leak

LEAK_RB = 0.04  # blue light seen by the red channel
LEAK_BR = 0.03  # red light seen by the blue channel


def _slanted_bands(H, W, B, L, w, sigma, offset, slant):
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    d = (xx - offset - slant * yy + B / 2) % B - B / 2
    return np.vectorize(pixel_value)(d, L, w, sigma)


@pytest.fixture(scope="module")
def two_pattern_light():
    """Red and blue band patterns at different positions, with an albedo ramp (no leak yet).

    Short bands at wide intervals, slanted differently: many bands of one pattern
    fall into clean gaps of the other.
    """
    H, W = 240, 800
    albedo = 60.0 + 120.0 * (np.arange(H)[:, None] / H)
    red = albedo * _slanted_bands(H, W, 44.0, 6.0, 2.5, 1.0, 5.0, 0.13)
    blue = albedo * _slanted_bands(H, W, 38.0, 5.0, 2.5, 1.0, 11.0, -0.07)
    return red, blue


def _camera_image(red, blue, ambient=8.0):
    R = ambient + red + LEAK_RB * blue
    G = ambient + 0.05 * (red + blue)
    Bc = ambient + blue + LEAK_BR * red
    return np.stack([R, G, Bc], axis=-1)


@pytest.mark.parametrize("kind", ["uint8", "uint16", "float"])
def test_estimate_leak(two_pattern_light, kind):
    img = _camera_image(*two_pattern_light)
    rng = np.random.default_rng(4)
    img = img + rng.normal(0.0, 1.0, img.shape)
    if kind == "uint8":
        img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    elif kind == "uint16":
        img = np.clip(np.rint(img * 257.0), 0, 65535).astype(np.uint16)
    rb = estimate_leak(img, 0, 2)
    br = estimate_leak(img, 2, 0)
    print(f"\n{kind}: leak blue->red {rb:.4f} (true {LEAK_RB}), "
          f"red->blue {br:.4f} (true {LEAK_BR})")  # fmt: skip
    assert abs(rb - LEAK_RB) <= 0.01
    assert abs(br - LEAK_BR) <= 0.01


def test_estimate_leak_into_a_dense_pattern():
    """Red lines 20 px apart, blue 60 px: no red gap holds a whole blue band with its floor
    on both sides (the estimate used to need that, and gave none here); the parts of the
    red gaps that blue bands cross give it."""
    H, W = 240, 800
    red = 150.0 * _slanted_bands(H, W, 20.0, 2.0, 2.5, 0.8, 3.0, 0.05)
    blue = 150.0 * _slanted_bands(H, W, 60.0, 4.0, 5.0, 0.8, 17.0, -0.04)
    img = _camera_image(red, blue) + np.random.default_rng(6).normal(0.0, 1.0, (H, W, 3))
    img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    rb = estimate_leak(img, 0, 2, (41, 121))
    br = estimate_leak(img, 2, 0, (121, 41))
    print(f"\nleak blue->red {rb:.4f} (true {LEAK_RB}), red->blue {br:.4f} (true {LEAK_BR})")
    assert abs(rb - LEAK_RB) <= 0.005
    assert abs(br - LEAK_BR) <= 0.005


# ------------------------------------------------------------------ blur from short bands


def test_blur_fit_from_short_bands_only():
    """A frame of short bands only (fan at 1 ms): sweeps 1-7 px longer than the line.

    sigma^2 = a + b scale^2 with a camera term a = 0.36 and projector defocus
    b = 0.36 (projector px^2), lines 3 projector px wide, at three magnifications.
    The fit must recover sigma at every magnification (the old fit needed bands
    longer than 2 w + 4 px and returned nothing here).
    """
    rng = np.random.default_rng(5)
    a_true, b_true = 0.36, 0.36
    ms, rs, lines, scales = [], [], [], []
    for _ in range(36):
        s = rng.choice([1.0, 1.5, 2.0])
        w = 3.0 * s
        sigma = float(np.sqrt(a_true + b_true * s * s))
        L = w + rng.uniform(1.0, 7.0)
        b = render_and_detect(L, w, sigma, gap_for(L, w, sigma) + rng.uniform(0, 5), rng.uniform())
        b = b[1:-1]
        ms.append(b[:, F_LENGTH])
        rs.append(b[:, F_RAMP])
        lines.append(np.full(len(b), w))
        scales.append(np.full(len(b), s))
    fit = fit_blur(*(np.concatenate(v) for v in (ms, rs, lines, scales)))
    assert fit is not None
    a, b = fit
    for s in (1.0, 1.5, 2.0):
        want = np.sqrt(a_true + b_true * s * s)
        got = np.sqrt(a + b * s * s)
        print(f"scale {s}: sigma {got:.3f} (true {want:.3f})")
        assert abs(got - want) <= 0.04 * want


def test_joint_length_recovers_sweeps_around_the_line_width():
    """Sweeps from 0.6 to 1.6 line widths: the width alone cannot tell them (NaN or a
    jump with the phase); width and ramp together recover them, unbiased over phases."""
    rng = np.random.default_rng(3)
    t = tables()
    worst_mean, worst = 0.0, 0.0
    for _ in range(14):
        w = rng.uniform(3.0, 6.5)
        sigma = rng.uniform(0.8, 1.5)
        L = w * rng.uniform(0.6, 1.6)
        rec = []
        for phase in np.arange(8) / 8:
            b = render_and_detect(L, w, sigma, gap_for(L, w, sigma), phase)[1:-1]
            rec.append(t.joint_length(b[:, F_LENGTH], b[:, F_RAMP], w, sigma))
        rel = np.concatenate(rec) / L - 1
        assert np.all(np.isfinite(rel))
        worst_mean = max(worst_mean, abs(rel.mean()))
        worst = max(worst, np.abs(rel).max())
    print(f"\njoint length: worst mean error {100 * worst_mean:.2f} %, "
          f"worst band {100 * worst:.2f} %")  # fmt: skip
    assert worst_mean <= 0.02  # measured 1.6 %
    assert worst <= 0.07  # measured 5.9 %


def _upright_band_image(rng, noise=0.0):
    """A 60x120 two-channel-like RGB image of upright trapezoid bands (8-bit)."""
    x = np.arange(120.0)
    row = np.clip(np.minimum(x % 30 - 4, 18 - x % 30) / 4, 0, 1)  # ramps of 4 px, plateau 6
    img = np.repeat((20 + 180 * row)[None, :], 60, axis=0)
    img = np.stack([img, np.full_like(img, 10), img[:, ::-1]], axis=2)
    img = img + noise * rng.standard_normal(img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def test_fill_print_restores_bands_under_small_print_and_leaves_the_rest():
    rng = np.random.default_rng(3)
    clean = _upright_band_image(rng)
    printed = clean.copy()
    # glyph-like specks, 2-5 rows tall, inked to 10-30 % albedo
    for _ in range(40):
        y, x = rng.integers(0, 55), rng.integers(0, 117)
        hgt, wid = rng.integers(2, 6), rng.integers(1, 4)
        printed[y : y + hgt, x : x + wid] = (printed[y : y + hgt, x : x + wid]
                                             * rng.uniform(0.1, 0.3)).astype(np.uint8)  # fmt: skip
    filled = fill_print(printed, 13, min_dip=6.0)
    assert np.array_equal(filled[6:-6], clean[6:-6])
    # monotone ramps, plateaus and a dark area taller than the segment are left alone
    dark = clean.copy()
    dark[20:40] //= 8
    assert np.array_equal(fill_print(dark, 13, min_dip=6.0), dark)
    # noise is not a dip: a noisy image comes back all but unchanged (0.2-0.3 % of its
    # pixels measured, those of the rare 5-sigma dips)
    for sigma in (2.0, 6.0):
        noisy = _upright_band_image(rng, noise=sigma)
        assert np.mean(fill_print(noisy, 13, min_dip=6.0) != noisy) < 0.005
    # and print on a noisy image is still filled: within the noise of the clean bands
    noisy = _upright_band_image(rng, noise=2.0)
    ink = noisy.copy()
    ink[10:14, 50:53] //= 6
    diff = fill_print(ink, 13, min_dip=6.0)[10:14, 50:53].astype(int) - noisy[10:14, 50:53]
    assert np.abs(diff).max() <= 10
    assert fill_print(printed, 1, min_dip=6.0) is printed


def test_bands_further_apart_than_the_window_keep_their_interval():
    """Sparse lines with long gaps, the window learnt too short (a tilted board's pattern).

    In a gap longer than the sliding window the mid-level cuts the noise into faint
    "bands"; the real bands' neighbours are past them (once: every band was
    irregular, for want of a neighbour).
    """
    rng = np.random.default_rng(5)
    B, L, w, sigma = 150.0, 28.0, 4.0, 1.2
    c = centres_for(B, 6, 0.4)
    v = band_row(int(c[-1] + 80), c, L, w, sigma) + rng.normal(0.0, 0.6, int(c[-1] + 80))
    img = np.ascontiguousarray(np.repeat(np.repeat(v[None, :, None], 3, 0), 3, 2))
    bands = np.empty((1, 1, MAX_BANDS, N_FIELDS))
    counts = np.empty((1, 1), np.int64)
    detect_bands(img, WEIGHTS, np.array([1], np.int64), np.array([67], np.int64), 255.0,
                 PARAMS, NO_EDGE, bands, counts)  # fmt: skip
    b = bands[0, 0, : counts[0, 0]]
    valid = b[b[:, F_VALID] == 1.0]
    assert len(valid) >= 4  # the interior ones (and more)
    np.testing.assert_allclose(valid[:, F_INTERVAL], B, rtol=0.01)
    np.testing.assert_allclose(valid[:, F_LENGTH], L, rtol=0.02)


def test_band_beside_a_depth_edge_takes_the_interval_of_its_own_side():
    """Bands 40 px apart on an object, 20 px apart on the wall behind it.

    The two bands at the edge have spacings that disagree (40 and 30, 30 and 20): each
    takes its interval from the two neighbours on its own side, where the spacings
    agree (once: both were irregular, as are many of a fan blade's bands).
    """
    obj = centres_for(40.0, 4)
    wall = obj[-1] + 30.0 + 20.0 * np.arange(4)
    L = {40.0: 14.0, 20.0: 6.0}
    v = np.full(int(wall[-1] + 60), BG)
    for cs, B in ((obj, 40.0), (wall, 20.0)):
        v += band_row(v.size, cs, L[B], 4.0, 1.0) - BG
    b = detect_row(v, 30.0)
    assert len(b) == 8
    np.testing.assert_array_equal(b[1:7, F_VALID], 1.0)
    np.testing.assert_allclose(b[1:4, F_INTERVAL], 40.0, rtol=0.01)
    np.testing.assert_allclose(b[4:7, F_INTERVAL], 20.0, rtol=0.01)
    np.testing.assert_allclose(b[1:4, F_LENGTH], 14.0, rtol=0.02)


def test_fill_print_on_some_rows_fills_them_as_the_whole_image_does():
    """Only the detector's rows are closed (the erosion runs on them alone): the same values."""
    rng = np.random.default_rng(5)
    printed = _upright_band_image(rng, noise=2.0)
    printed[10:14, 50:53] //= 6
    printed[0:3, 20:30] //= 5  # print at the top border, where the erosion is clipped
    whole = fill_print(printed, 13, min_dip=6.0)
    rows = np.array([0, 1, 5, 11, 12, 30, printed.shape[0] - 1])
    part = fill_print(printed, 13, min_dip=6.0, rows=rows)
    assert np.array_equal(part[rows], whole[rows])
    # the other rows are the image's own
    assert np.array_equal(np.delete(part, rows, axis=0), np.delete(printed, rows, axis=0))
    assert not np.array_equal(whole[rows], printed[rows])  # some print was filled there


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("min_dip", [6.5, 7.5, 12.0])
def test_fill_print_on_some_rows_rounds_as_opencv_does(dtype, min_dip):
    """The rows' one-pass kernel against OpenCV's closing of the whole image, in 8 and 16
    bits, where the shallowest dip filled is halfway between two integers (rounded half to
    even, as OpenCV rounds a scalar) and where the eighths of the closing tie."""
    rng = np.random.default_rng(7)
    printed = _upright_band_image(rng, noise=3.0).astype(dtype)
    if dtype == np.uint16:
        printed = printed * np.uint16(16) + rng.integers(0, 16, printed.shape, dtype=np.uint16)
    printed[10:14, 50:53] //= 6
    printed[30:33, 80:90] //= 3
    whole = fill_print(printed, 13, min_dip=min_dip)
    rows = np.arange(printed.shape[0])
    assert np.array_equal(fill_print(printed, 13, min_dip=min_dip, rows=rows), whole)
    assert not np.array_equal(whole, printed)
    # an eighth of the closing halfway between two integers: 100 / 8 rounds down to 12,
    # 108 / 8 up to 14 (half to even), so a dip of 13 is filled on 100, one of 14 is not
    # on 108, one of 15 is
    flat = np.full((30, 12, 3), 100, dtype)
    flat[:, 6:] = 108
    flat[15, 1] -= 13
    flat[15, 8] -= 14
    flat[15, 10] -= 15
    whole = fill_print(flat, 13, min_dip=1.0)
    assert np.array_equal(fill_print(flat, 13, min_dip=1.0, rows=rows[:30]), whole)
    assert whole[15, 1, 0] == 100 and whole[15, 8, 0] == 108 - 14 and whole[15, 10, 0] == 108


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("n", [1, 2, 7, 1000, 1001])
def test_median_from_a_histogram_equals_numpys(dtype, n):
    top = 200 if dtype == np.uint8 else 4000
    values = np.random.default_rng(n).integers(0, top, n).astype(dtype)
    assert histogram_median(values) == float(np.median(values))


def test_outermost_band_where_the_lines_bunch_waits_for_its_arc():
    """The outermost band's interval is extrapolated from its two spacings on one side.

    Where the lines bunch towards a ball's limb the spacing grows faster than linearly and
    that extrapolation comes out short: on the matrix's balls, -4 to -8 % against the
    renderer's truth (-12 % on gen2026's sparse pattern), which read those bands' sweeps
    10-30 % long, a one-sided depth bias (issue 8).  A spacing change of more than half the
    interval tolerance there marks the band a limb band, without an interval until
    :mod:`lightflow.app.core.arcs` gives it one; spacings that change linearly (a tilted
    plane, within 2 %) keep their extrapolated interval.
    """
    L, w, sigma = 14.0, 4.0, 1.0
    limb = FIRST + np.cumsum([0.0, 40.0, 40.0, 40.0, 44.0, 50.0, 60.0])
    plane = FIRST + np.cumsum([0.0, 40.0, 42.0, 44.0, 46.0, 48.0])
    for centres in (limb, plane):
        b = detect_row(band_row(int(centres[-1] + 80), centres, L, w, sigma), 45.0)
        assert len(b) == len(centres)
        np.testing.assert_array_equal(b[:-1, F_VALID], 1.0)
        np.testing.assert_allclose(b[:-1, F_LENGTH], L, rtol=0.02)
        # the spacing beyond the last band, extrapolated linearly
        np.testing.assert_allclose(b[-1, F_INTERVAL], 1.5 * (centres[-1] - centres[-2])
                                   - 0.5 * (centres[-2] - centres[-3]), atol=0.05)  # fmt: skip
    limb_row = band_row(int(limb[-1] + 80), limb, L, w, sigma)
    assert detect_row(limb_row, 45.0)[-1, F_VALID] == BAND_LIMB
    b = detect_row(band_row(int(plane[-1] + 80), plane, L, w, sigma), 45.0)
    assert b[-1, F_VALID] == 1.0
    assert b[-1, F_INTERVAL] == pytest.approx(49.0, abs=0.05)


def _sphere_row_centres(R, tilt_deg, pitch, x0, x1):
    """Line centres along a row across a sphere (orthographic), and the true interval at each.

    The projector, tilted by ``tilt_deg`` in the row's plane, casts lines ``pitch`` apart in
    ``u = x cos(t) - sqrt(R^2 - x^2) sin(t)``: towards ``x = R`` the lines bunch ever faster.
    """
    t = np.radians(tilt_deg)
    x = np.linspace(x0, x1, 20001)
    u = x * np.cos(t) - np.sqrt(R * R - x * x) * np.sin(t)
    lines = np.arange(np.ceil(u[0] / pitch), np.floor(u[-1] / pitch) + 1) * pitch
    xs = np.interp(lines, u, x)  # u grows with x here
    du_dx = np.cos(t) + np.sin(t) * xs / np.sqrt(R * R - xs * xs)
    return FIRST + 40.0 + xs - xs[0], pitch / du_dx


def test_bands_whose_spacing_changes_smoothly_keep_an_interval_from_the_line_density():
    """Lines bunching towards a ball's limb: spacings that differ by more than the interval
    tolerance, changing as a smooth trend, are no depth edge (issue 8: most of the balls'
    pixels were irregular).  Such a band takes its interval from the lines' density,
    interpolated quadratically from four lines; the mean spacing is 3-6 % long there.  A
    step of the spacing stays irregular.
    """
    L, w, sigma = 8.0, 4.0, 1.0
    worst = worst_mean = 0.0
    kept = 0
    for R, tilt, pitch, x1 in ((150.0, 35.0, 55.0, 0.92), (200.0, 40.0, 60.0, 0.9),
                               (150.0, 35.0, 40.0, 0.97)):  # fmt: skip
        centres, truth = _sphere_row_centres(R, tilt, pitch, -0.6 * R, x1 * R)
        b = detect_row(band_row(int(centres[-1] + 80), centres, L, w, sigma), 45.0)
        assert len(b) == len(centres)
        d = np.diff(centres)
        fast = np.abs(d[1:] - d[:-1]) > 0.25 * 0.5 * (d[1:] + d[:-1])  # beyond the tolerance
        inner = np.arange(1, len(b) - 1)
        np.testing.assert_array_equal(b[inner, F_VALID], 1.0)
        rel = b[inner, F_INTERVAL] / truth[inner] - 1
        kept += np.count_nonzero(fast)
        worst = max(worst, np.abs(rel[fast]).max(initial=0.0))
        # the mean spacing, as the bands with spacings within the tolerance have it
        mean = 0.5 * (d[1:] + d[:-1])[fast] / truth[inner][fast] - 1
        worst_mean = max(worst_mean, np.abs(mean).max(initial=0.0))
    print(f"\nsmooth spacing: {kept} bands beyond the tolerance, worst interval "
          f"{100 * worst:.1f} % (the mean spacing {100 * worst_mean:.1f} %)")  # fmt: skip
    assert kept >= 3
    assert worst < worst_mean
    assert worst <= 0.035  # measured 3.0 % (at 0.97 R: the limb itself), else within 2.4 %
    # a step of the spacing (an object before a wall): 40, 40 | 58, 58; a step with the
    # spacings on either side changing the other way: irregular.  A step more than twice
    # the change (as a log ratio) beside it, smaller than STEEP_CHANGE: no interval until
    # the arcs tell a fast bend from a depth edge (test_arcs)
    for spacings, code in (((40.0, 40.0, 58.0, 58.0), BAND_IRREGULAR),
                           ((44.0, 40.0, 58.0, 54.0), BAND_IRREGULAR),
                           ((34.0, 40.0, 58.0, 70.0), BAND_STEEP)):  # fmt: skip
        centres = FIRST + np.cumsum([0.0, *spacings])
        b = detect_row(band_row(int(centres[-1] + 80), centres, 14.0, w, sigma), 45.0)
        assert b[2, F_VALID] == code, spacings
    # beyond STEEP_CHANGE it is a step
    centres = FIRST + np.cumsum([0.0, 30.0, 36.0, 60.0, 75.0])
    b = detect_row(band_row(int(centres[-1] + 80), centres, 14.0, w, sigma), 45.0)
    assert b[2, F_VALID] == BAND_IRREGULAR


def test_neighbours_swept_longer_are_lower_but_carry_the_same_light():
    """A line swept 2.8 times as long is 2.8 times lower (on a ball the sweeps change from
    line to line): its neighbours' light, height times width, is what must agree.  A band
    beside one with a quarter of its light stays irregular."""
    w, sigma = 4.0, 1.0
    centres = centres_for(45.0, 7)
    sweeps = [10.0, 28.0, 10.0, 28.0, 10.0, 28.0, 10.0]
    n = int(centres[-1] + 60)
    v = np.full(n, BG)
    for c, L in zip(centres, sweeps, strict=True):
        # over the exposure a line's light spreads along its sweep
        v += band_row(n, [c], L, w, sigma, amp=AMP * 10.0 / L) - BG
    # a window shorter than the interval: each band is found against its own level
    b = detect_row(v, 25.0)
    assert len(b) == 7
    np.testing.assert_array_equal(b[1:6, F_VALID], 1.0)
    heights = b[1:6, F_HEIGHT]
    assert heights.max() > 2.5 * heights.min()  # the heights alone would have rejected them
    np.testing.assert_allclose(b[1:6, F_LENGTH], sweeps[1:6], rtol=0.02)
    dim = np.full(n, BG)
    for k, c in enumerate(centres):
        dim += band_row(n, [c], 14.0, w, sigma, amp=AMP / 4 if k == 3 else AMP) - BG
    b = detect_row(dim, 25.0)
    assert len(b) == 7
    np.testing.assert_array_equal(b[2:5, F_VALID], BAND_IRREGULAR)
    np.testing.assert_array_equal(b[[1, 5], F_VALID], 1.0)


@pytest.mark.xfail(
    strict=True,
    reason="profile_model: sweeps of 0.5-0.8 line widths, read from width and ramp through "
    "the joint table, come out 2-9 % short on average over phases on exactly rendered bands "
    "(w=3, sigma=0.81: -8.7 % at half a line width; w=5.7, sigma=1.28: -4.3 %); the argmin "
    "over the detector's own curve at the same (w, sigma) is mostly within 2 %.  A finer ramp axis "
    "(0.05 px) or sweep axis (0.25 px) did not change it.  The sparse pattern's sweeps on "
    "the matrix's balls are 0.5-0.9 line widths: -2 to -3 % there, the remaining negative "
    "ball bias (issue 8).  Cause (nineteenth session): a narrow line is undersampled, and the "
    "(m, r) the detector reports vary with the band's sub-pixel phase as much as with L (w=3, "
    "sigma=0.75, L=1.5: m 3.24-3.42 px, r 0.70-0.85 px over 8 phases), so inverting the "
    "phases' mean curve is biased; the mean of each phase's argmin (8.9 %) and the argmin over "
    "every phase's curve (9.2 %) are no better, nor a plateau continuous in the phase (9.2 %). "
    "Left: a reading that knows the band's phase (its centre gives it; "
    "docs/experiments/short-sweep-phase.md)",
)
def test_sweeps_of_half_a_line_width_read_unbiased():
    t = tables()
    worst = 0.0
    for w, sigma in ((3.0, 0.81), (4.2, 1.03), (5.7, 1.28)):
        for L in (0.5 * w, 0.65 * w, 0.8 * w):
            rec = []
            for phase in np.arange(8) / 8:
                b = render_and_detect(L, w, sigma, 5 * w + 40, phase)
                b = b[b[:, F_VALID] > 0][1:-1]
                rec.append(t.joint_length(b[:, F_LENGTH], b[:, F_RAMP], w, sigma))
            worst = max(worst, abs(np.mean(np.concatenate(rec)) / L - 1))
    print(f"\nshort sweeps: worst mean error {100 * worst:.1f} %")
    assert worst <= 0.015


def test_upright_tiles_judge_a_tile_by_the_mean_slant_of_its_bands():
    """Single slants scatter (print, two rows a few rows apart): the tile's mean decides.

    Left half: upright lines whose slants scatter by 0.04 with a few wild ones (print cut
    their bands); right half: lines slanted by 0.08 (a tilted board), the same scatter.
    """
    rng = np.random.default_rng(4)
    h, w, tile = 512, 1024, 128
    row_y = np.arange(2, h, 4)
    centres = np.arange(10.0, w, 20.0)
    bands = np.full((len(row_y), 64, N_FIELDS), np.nan)
    counts = np.full(len(row_y), len(centres))
    bands[:, : len(centres), F_CENTRE] = centres
    bands[:, : len(centres), F_VALID] = 1.0
    slant = np.where(centres < w / 2, 0.0, 0.08) + rng.normal(0.0, 0.04, (len(row_y), len(centres)))
    wild = rng.random(slant.shape) < 0.05
    slant[wild] = rng.choice([-1.0, 1.0], wild.sum())
    bands[:, : len(centres), F_SLANT] = slant
    # no valid band in the last tile row: it is judged by those of the row above
    bands[row_y >= 384, : len(centres), F_VALID] = -2.0
    up = upright_tiles(bands, counts, row_y, (h, w), tile, 2.0 / 80)
    assert up.shape == (4, 8)
    assert up[:, :3].all()  # the upright half, and its tiles pooled with each other
    assert not up[:, 5:].any()  # slanted: even pooled with an upright neighbour
    # without any valid band near, no tile is upright
    bands[:, : len(centres), F_VALID] = -2.0
    assert not upright_tiles(bands, counts, row_y, (h, w), tile, 2.0 / 80).any()
