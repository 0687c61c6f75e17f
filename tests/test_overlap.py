"""Sweeps of bands longer than the line interval (app/core/overlap.py).

Rows rendered from the band model itself (profile_model.pixel_value, energy
conserving: a band of sweep L has height I w / L) and from the independent
simulator (a board moving along the axis, lit by a projector parallel to the
camera, so that the line interval and the sweep are the same along a row).
"""

from __future__ import annotations

import numpy as np
import pytest

from lightflow.app.core.bands import (
    BAND_PERIODIC,
    F_CENTRE,
    F_HEIGHT,
    F_INTERVAL,
    F_LENGTH,
    F_VALID,
    N_FIELDS,
    BandParams,
    detect_bands,
)
from lightflow.app.core.overlap import (
    O_CODE,
    O_FRACTION,
    O_PULSE,
    O_SWEEP,
    OV_AMBIGUOUS,
    OV_FLAT,
    OV_IRREGULAR,
    OV_MEASURED,
    OV_SHORT,
    OverlapParams,
    line_centred,
    measure_runs,
    measure_stretches,
    refine_interval,
)
from lightflow.app.core.profile_model import pixel_value

B, W, SIGMA, INTENSITY, BG = 30.0, 4.0, 1.0, 200.0, 10.0
#: stretch length in line intervals
PERIODS = 4


def periodic_row(n, interval, L, w, sigma, intensity=INTENSITY, bg=BG, first=5.0):
    """Background plus bands ``interval`` apart, each ``intensity * w / L`` high."""
    v = np.full(n, bg)
    reach = int(0.5 * (L + w) + 6 * sigma + 3)
    for c in np.arange(first - 4 * interval, n + 4 * interval, interval):
        for j in range(max(0, int(c) - reach), min(n, int(c) + reach + 2)):
            v[j] += intensity * w / max(L, 1e-3) * pixel_value(j - c, L, w, sigma)
    return v


def model_rows(us, noise, seed=1, phases=(0.0, 0.37)):
    rng = np.random.default_rng(seed)
    n = int(PERIODS * B)
    rows, truth = [], []
    for u in us:
        for ph in phases:
            v = periodic_row(n, B, u * B, W, SIGMA, first=5.0 + ph * B)
            rows.append(v + rng.normal(0.0, noise, n))
            truth.append(u * B)
    return np.array(rows), np.array(truth)


def measure(rows, **refs):
    k = len(rows)
    return measure_stretches(rows, np.arange(k), np.zeros(k, int), np.full(k, rows.shape[1]),
                             B, W, SIGMA, **refs)  # fmt: skip


def near_integer(u, d):
    return np.abs(u - np.round(u)) < d


US = np.round(np.arange(0.5, 2.501, 0.05), 3)


@pytest.mark.parametrize("noise", [0.0, 1.0])
def test_model_rows_give_the_sweep_within_one_percent_or_nan(noise):
    rows, L = model_rows(US, noise)
    out = measure(rows, bg=BG)
    u = L / B
    got = out[:, O_SWEEP]
    ok = np.isfinite(got)
    err = np.abs(got[ok] - L[ok]) / L[ok]
    print(f"\nnoise {noise}: {ok.sum()} of {len(L)} measured, max |error| {100 * err.max():.3f} %")
    # measured: noise-free 1e-6 %; 1 DN (band height 13-53 DN): at most 0.8 %
    assert err.max() < (1e-4 if noise == 0 else 0.01)
    assert np.all(out[ok, O_CODE] == OV_MEASURED)
    # at integer L / B the row is flat: never a number there
    assert not ok[near_integer(u, 0.051)].any()
    assert np.all(out[near_integer(u, 0.051), O_CODE] == OV_FLAT)
    # away from integers nearly everything is measured (noise-free: all with f in 0.2-0.8;
    # 1 DN: 52 of 54 with 4 intervals)
    mid = ~near_integer(u, 0.19)
    assert ok[mid].mean() > (0.99 if noise == 0 else 0.9)


def test_integer_part_from_prior_parity_or_nothing():
    us = np.array([0.6, 1.3, 1.6, 2.4])
    rows, L = model_rows(us, 0.5, phases=(0.0,))
    u = L / B
    # a coarse prior within a quarter of an interval
    out = measure(rows, prior=u + np.array([0.25, -0.25, 0.2, -0.2]))
    assert np.allclose(out[:, O_SWEEP], L, rtol=0.01)
    # no reference at all: the fraction is known, the sweep is not
    out = measure(rows)
    assert np.all(out[:, O_CODE] == OV_AMBIGUOUS) and np.isnan(out[:, O_SWEEP]).all()
    assert np.allclose(out[:, O_FRACTION], u % 1.0, atol=0.01)
    # a prior half an interval off cannot place n
    out = measure(rows, prior=u + 0.5)
    assert np.all(out[:, O_CODE] == OV_AMBIGUOUS)
    # the line centre (5.0 + k B) fixes the parity of n: then a prior 0.7 off still works
    out = measure(rows, prior=u + 0.7, centre=5.0)
    assert np.allclose(out[:, O_SWEEP], L, rtol=0.01)
    pulse = out[:, O_PULSE]
    odd = np.abs(((pulse - 5.0) / B) % 1.0 - 0.5) < 0.1
    assert np.array_equal(odd, np.floor(u).astype(int) % 2 == 1)


def test_integer_part_from_the_background_and_its_limit():
    us = np.array([0.7, 1.4, 2.3])
    rows, L = model_rows(us, 0.5, phases=(0.0,))
    assert np.allclose(measure(rows, bg=BG)[:, O_SWEEP], L, rtol=0.01)
    # background and prior disagree by an interval: no answer rather than a wrong one
    out = measure(rows, bg=BG, prior=L / B + 1.0)
    assert np.all(out[:, O_CODE] == OV_AMBIGUOUS)
    # a background off by half a band height (h = I w / L, 11-38 DN here) is refused
    h = INTENSITY * W / L
    out = measure(rows, bg=BG + 0.5 * h)
    assert np.all(out[:, O_CODE] == OV_AMBIGUOUS)
    # so is a right background known only to half a band height
    out = measure(rows, bg=BG, bg_err=0.5 * h)
    assert np.all(out[:, O_CODE] == OV_AMBIGUOUS)


def test_a_row_that_is_not_periodic_is_not_measured():
    n = int(PERIODS * B)
    v = periodic_row(n, B, 1.4 * B, W, SIGMA)
    edge = v.copy()
    edge[n // 2 :] = 0.4 * (edge[n // 2 :] - BG) + BG  # darker print on half of the stretch
    chirp = periodic_row(n, B, 1.4 * B, W, SIGMA)
    x = np.arange(n)
    chirp = np.interp(x * 1.12 - 0.06 * x * x / n, x, chirp)  # interval changes by 12 %
    rows = np.array([edge, chirp])
    out = measure(rows, bg=BG)
    print(f"\ncodes {out[:, O_CODE]}")
    assert np.isnan(out[:, O_SWEEP]).all()
    assert set(out[:, O_CODE]) <= {OV_IRREGULAR, OV_FLAT}
    # a stretch shorter than two intervals is not fitted
    out = measure_stretches(v[None], [0], [0], [int(1.8 * B)], B, W, SIGMA, bg=BG)
    assert out[0, O_CODE] == OV_SHORT


def test_refine_interval():
    n = int(PERIODS * B)
    v = periodic_row(n, B, 1.4 * B, W, SIGMA)
    assert refine_interval(v, 0, n, 0.96 * B) == pytest.approx(B, rel=1e-5)
    for seed in range(5):
        noisy = v + np.random.default_rng(seed).normal(0, 1.0, n)
        # measured: within 0.31 % over 4 intervals with 1 DN of noise
        assert refine_interval(noisy, 0, n, 1.03 * B) == pytest.approx(B, rel=5e-3)


def test_params_are_frozen():
    p = OverlapParams()
    with pytest.raises(AttributeError):
        p.max_rel_std = 0.1  # type: ignore[misc]


# ---------------------------------------------------------------- the simulator


@pytest.fixture(scope="module")
def parallel_rig():
    """The two-projector rig, cropped to 8 rows; its blue projector parallel to the camera.

    With the projector's axis parallel to the camera's (a lens-shifted projector
    aimed by its principal point), a board facing the camera shows one line
    interval along the whole row and moves every line by the same amount.
    """
    from lightflow.app.core.rig import resolve_rig, rig_from_dict

    d = resolve_rig("two-projector").to_dict()
    d["camera"]["height"] = 8
    d["camera"]["K"][1][2] -= 600 - 4
    p = d["projectors"][1]
    p["R"] = np.eye(3).tolist()
    p["t"] = [-0.25, 0.0, 0.0]
    p["K"][0][2] += 1500 * 0.25 / 0.7
    return rig_from_dict(d)


#: (exposure s, measurable): the board at 0.66 m moving away at 0.6 m/s; L / B =
#: 0.56, 0.97, 1.37, 1.50, 2.02, 2.39
SIM_CASES = ((0.02, True), (0.035, False), (0.05, True), (0.055, True), (0.075, False),
             (0.09, True))  # fmt: skip


def test_simulated_rows_give_the_sweep_within_one_percent_or_nan(parallel_rig):
    from lightflow.app.stages import true_flows
    from lightflow.drivers.sim.scenes import get_scene
    from lightflow.drivers.sim.synthetic import SceneRenderer

    renderer = SceneRenderer(parallel_rig, get_scene("board"))
    q = 1  # the blue pattern: pitch 18, width 3 projector px
    shares = []
    for exposure, measurable in SIM_CASES:
        image = renderer.expose(renderer.radiance(0.1, exposure), np.random.default_rng(0))
        flows = true_flows(renderer, 0.1, exposure)
        # four rows averaged (the lines are upright), as the detector's rows_per_cell does
        row = image[2:6, :, 2].astype(np.float64).mean(axis=0)
        interval = float(np.nanmedian(flows.interval[q, 4, 200:1400]))
        sweep = float(np.nanmedian(flows.sweep[q, 4, 200:1400]))
        line = float(np.nanmedian(flows.line[q, 4, 200:1400]))
        # the simulator's optics: lens 0.6 px, projector defocus 0.6 projector px
        sigma = float(np.hypot(0.6, 0.6 * interval / 18.0))
        n = int(PERIODS * interval)
        lo = np.arange(200, 1400 - n, int(interval) // 2)
        u = sweep / interval
        # a coarse prior (continuity), a quarter of an interval off
        out = measure_stretches(row[None], np.zeros(len(lo), int), lo, lo + n, interval, line,
                                sigma, prior=u + 0.25)  # fmt: skip
        got = out[:, O_SWEEP]
        ok = np.isfinite(got)
        err = np.abs(got[ok] / sweep - 1.0)
        print(f"\nexposure {exposure * 1e3:.0f} ms: L/B {u:.3f}, {ok.sum()} of {len(lo)} "
              f"measured, max |error| {100 * err.max() if ok.any() else np.nan:.2f} %")  # fmt: skip
        if measurable:
            assert err.max() < 0.01
            shares.append(ok.mean())
        else:
            assert not ok.any()
    print(f"measured shares {np.round(shares, 2)}")
    assert min(shares) > 0.5


def chirped_row(n, u, g, first=5.0):
    """Lines ``B (1 + g (x - xc))`` apart (``xc`` the middle), sweep and width in proportion."""
    tc = 0.5 * (n - 1)
    v = np.full(n, BG)
    for s in np.arange(first - 6 * B, n + 6 * B, B):
        c = tc + np.expm1(g * (s - tc)) / g
        local = B * (1.0 + g * (c - tc))
        L, w = u * local, W * local / B
        reach = int(0.5 * (L + w) + 6 * SIGMA + 3)
        for j in range(max(0, int(c) - reach), min(n, int(c) + reach + 2)):
            v[j] += INTENSITY * w / L * pixel_value(j - c, L, w, SIGMA)
    return v


def test_a_changing_interval_is_followed_when_given():
    """A toed-in projector: the interval changes 0.2 % per pixel (24 % over the stretch)."""
    n = int(PERIODS * B)
    g = 0.002
    us = np.array([0.6, 1.3, 1.5, 2.3])
    rng = np.random.default_rng(5)
    rows = np.array([chirped_row(n, u, g) + rng.normal(0, 0.5, n) for u in us])
    k = len(us)
    args = (rows, np.arange(k), np.zeros(k, int), np.full(k, n), B, W, SIGMA)
    out = measure_stretches(*args, bg=BG, chirp=g)
    err = out[:, O_SWEEP] / (us * B) - 1.0
    print(f"\nchirp given: errors {np.round(100 * err, 3)} %")
    assert np.all(np.abs(err) < 0.01)  # measured: at most 0.39 %
    # taken as constant, the same rows do not fit the periodic model: no number (a
    # change of 12 % over the stretch still gives the sweep within 0.25 % without it)
    plain = measure_stretches(*args, bg=BG)
    print(f"chirp ignored: codes {plain[:, O_CODE]}")
    assert np.isnan(plain[:, O_SWEEP]).all()


# ------------------------------------------------------------ runs of rejected bands

RUN_SETS = [(20.0, 2.0, 0.7), (20.0, 5.0, 1.4), (30.0, 3.0, 1.0), (40.0, 7.0, 0.6),
            (25.0, 3.0, 1.6), (16.0, 2.0, 0.8)]  # fmt: skip


def detect_and_measure_runs(B, w, sigma, L, phase, bg=(BG, BG), lines=14, split=None,
                            whole=False):  # fmt: skip
    """One rendered row (30 px of background at both ends) through the band detector and
    :func:`measure_runs`, with the blur and line width known: the first pattern's bands.
    ``bg``: the background before and after ``split`` (default: the row's middle).
    ``whole``: both patterns' ``(bands, counts)`` and the lines' trajectory centres."""
    c = 0.5 * (L + w) + 30.0 + phase + B * np.arange(lines)
    n = int(c[-1] + 0.5 * (L + w) + 30)
    v = np.where(np.arange(n) < (n // 2 if split is None else split), bg[0], bg[1]) * 1.0
    reach = int(0.5 * (L + w) + 6 * sigma + 3)
    for ck in c:
        for j in range(max(0, int(ck) - reach), min(n, int(ck) + reach + 2)):
            v[j] += 80.0 * pixel_value(j - ck, L, w, sigma)
    img = np.ascontiguousarray(np.repeat(np.repeat(v[None, :, None], 3, 0), 3, 2))
    weights = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    b = BandParams()
    params = np.array([b.min_contrast, b.interval_tolerance, b.symmetry_tolerance_px,
                       b.min_gap_px, b.vertical_extra])  # fmt: skip
    bands = np.empty((2, 1, 96, N_FIELDS))
    counts = np.empty((2, 1), np.int64)
    detect_bands(img, weights, np.array([1], np.int64), np.array([int(2 * B) | 1] * 2, np.int64),
                 255.0, params, np.zeros((2, 3)), bands, counts)  # fmt: skip
    measure_runs(img, weights, np.array([1]), bands, counts, np.array([w, w]),
                 np.array([B, B]), np.array([[sigma * sigma, 0.0]] * 2),
                 OverlapParams(max_rel_std=0.02))  # fmt: skip
    if whole:
        return bands, counts, c
    return bands[0, 0, : counts[0, 0]]


@pytest.mark.parametrize("B,w,sigma", RUN_SETS)
def test_runs_of_overlapping_bands_give_the_sweep_or_stay_rejected(B, w, sigma):
    """L from 0.5 to 2.5 intervals: bands are valid alone, or periodic within 0.5 % of L,
    or rejected.  Past one interval the floor on both sides of the run (the background)
    gives the integer part of L / B: most rows with L / B away from an integer are
    measured.  (A constant sweep: its pieces agree with the whole run, which keeps its
    reading; measured at most 0.32 %.)"""
    periodic = {True: 0, False: 0}
    rows = {True: 0, False: 0}
    for u in np.arange(0.5, 2.55, 0.05):
        L = u * B
        for phase in (0.0, 0.3, 0.6):
            b = detect_and_measure_runs(B, w, sigma, L, phase)
            per = b[:, F_VALID] == BAND_PERIODIC
            assert np.all(np.abs(b[per, F_LENGTH] / L - 1.0) <= 0.005), (u, phase)
            if u > 1.0:
                # past one interval the bands alone are never valid (the pulses)
                assert not np.any(b[:, F_VALID] == 1.0), (u, phase)
            periodic[u < 1.0] += int(per.any())
            rows[u < 1.0] += int(abs(u - round(u)) > 0.2)
    print(f"\nB={B} w={w} sigma={sigma}: rows with periodic runs {periodic} of rows with "
          f"L / B 0.2 or more from an integer {rows}")  # fmt: skip
    assert periodic[True] >= 1
    # measured: 78-87 of the 90 rows past one interval (all those 0.2 from an integer: 57)
    assert periodic[False] >= rows[False]


@pytest.mark.parametrize("B,w,sigma", RUN_SETS)
def test_line_centred_puts_every_measured_pulse_on_a_line(B, w, sigma):
    """A periodic run's pulses lie on the lines' trajectory centres for an even integer
    part of L / B and half-way between them for an odd one; :func:`line_centred` moves
    the latter onto a line (a triangulation read them as lines half an interval off: a
    held-out board before a wall, 22 mm short).  Measured: within 0.07 px of a line,
    0.31 px where L / B lies within 0.1 of an integer."""
    moved = kept = 0
    for u in np.arange(0.5, 2.55, 0.1):
        for phase in (0.0, 0.45):
            bands, counts, c = detect_and_measure_runs(B, w, sigma, u * B, phase, whole=True)
            out = line_centred(bands, counts)
            b = out[0, 0, : counts[0, 0]]
            per = b[:, F_VALID] == BAND_PERIODIC
            on = b[per, F_CENTRE]
            # the outermost pulses of a run whose L / B is near an integer (nearly filling
            # the interval) are the least sure
            bound = 0.1 if abs(u - round(u)) > 0.15 else 0.4
            assert np.all(np.abs(on[:, None] - c[None, :]).min(axis=1) < bound), (u, phase)
            odd = per & (np.floor(b[:, F_LENGTH] / b[:, F_INTERVAL]) % 2 == 1)
            moved += int(odd.sum())
            kept += int((per & ~odd).sum())
            if not odd.any():
                assert out is bands  # nothing to move: no copy
    assert moved > 0 and kept > 0


@pytest.mark.parametrize("w,sigma", [(3.0, 1.4), (4.0, 1.2)])
def test_tight_valid_bands_get_their_periodic_sweep(w, sigma):
    """Bands whose gaps are narrower than TIGHT_GAP_SIGMAS blur sigmas are valid alone
    but read 1-6 % short (the neighbours' tails in the gap): their runs are measured on
    the periodic profile, within 0.5 % (0.5 % at most, 0.05 % on average, measured).
    Bands with wider gaps keep their own reading."""
    B = 24.3
    for u in (0.72, 0.76, 0.8):
        for phase in (0.0, 0.25, 0.5, 0.75):
            # (a run's outermost bands have no neighbour on one side: measured alone)
            b = detect_and_measure_runs(B, w, sigma, u * B, phase)[2:-2]
            assert np.all(b[:, F_VALID] == BAND_PERIODIC), (u, phase)
            assert np.all(np.abs(b[:, F_LENGTH] / (u * B) - 1.0) <= 0.005), (u, phase)
    for u in (0.5, 0.6):
        b = detect_and_measure_runs(B, w, sigma, u * B, 0.3)[2:-2]
        assert np.all(b[:, F_VALID] == 1.0), u


@pytest.mark.parametrize("B,w,sigma", RUN_SETS[:3])
def test_runs_next_to_a_darker_surface_stay_rejected(B, w, sigma):
    """The lines lie on a surface whose background is one pulse height above that of a
    darker surface just before them: the floor under the run is the darker one's, which
    would place n one too high.  The two sides of the run show different floors, so n
    is not resolved and nothing is measured (on one background the same rows are)."""
    measured = {0.0: 0, 1.0: 0}
    for u in np.arange(1.2, 2.55, 0.1):
        if abs(u - round(u)) < 0.15:
            continue
        L = u * B
        h = 80.0  # the pulses' height (the rows are drawn 80 high)
        for step in measured:
            b = detect_and_measure_runs(B, w, sigma, L, 0.3, bg=(BG, BG + step * h), lines=8,
                                        split=20)  # fmt: skip
            per = b[:, F_VALID] == BAND_PERIODIC
            assert np.all(np.abs(b[per, F_LENGTH] / L - 1.0) <= 0.005), (u, step)
            measured[step] += int(per.any())
    print(f"\nB={B}: rows measured by the background step (share of h) {measured}")
    assert measured[1.0] == 0
    assert measured[0.0] > 0


@pytest.mark.parametrize("B,w,sigma", RUN_SETS[:3])
def test_pulses_beyond_the_floors_reach_are_not_taken_for_bands(B, w, sigma):
    """A row of 30 lines swept past their neighbours: the bands in its middle are too far
    from a clean gap for the detector's floor test and look like short bands.  They
    continue the pulse train of the runs measured at the row's ends, so they are
    rejected: where a run is measured, every band left valid is periodic, with the sweep
    within 0.5 %.  (Where none is, they stay valid, a whole number of intervals short:
    the detector's limit.)"""
    rows = 0
    for u in np.arange(1.2, 2.55, 0.1):
        if abs(u - round(u)) < 0.15:
            continue
        L = u * B
        b = detect_and_measure_runs(B, w, sigma, L, 0.3, lines=30)
        ok = b[:, F_VALID] > 0.0
        if not np.any(b[:, F_VALID] == BAND_PERIODIC):
            continue
        rows += 1
        assert np.all(b[ok, F_VALID] == BAND_PERIODIC), u
        assert np.all(np.abs(b[ok, F_LENGTH] / L - 1.0) <= 0.005), u
    print(f"\nB={B}: rows with a measured run {rows}")
    assert rows >= 5


def detect_and_measure_rows(B, w, sigma, L, rows):
    """Rendered rows through the detector and :func:`measure_runs` (blur and line width
    known); ``rows`` gives per row the range of line indices drawn (line ``k`` at the same
    column in every row).  Returns the first pattern's bands and counts."""
    first, last = min(a for a, _ in rows), max(b for _, b in rows)
    x0 = 0.5 * (L + w) + 30.0 + 0.3  # the left-most line of the narrowest rows
    n = int(x0 + B * max(b for _, b in rows if (_ >= 0)) + 0.5 * (L + w) + 30)
    img = np.empty((len(rows), n, 3))
    reach = int(0.5 * (L + w) + 6 * sigma + 3)
    for i, (a, b) in enumerate(rows):
        v = np.full(n, BG)
        for k in range(max(a, first), min(b, last) + 1):
            ck = x0 + B * k
            for j in range(max(0, int(ck) - reach), min(n, int(ck) + reach + 2)):
                v[j] += 80.0 * pixel_value(j - ck, L, w, sigma)
        img[i] = v[:, None]
    img, weights, row_y, bands, counts = detect_rows(img[:, :, 0], B)
    measure_runs(img, weights, row_y, bands, counts, np.array([w, w]), np.array([B, B]),
                 np.array([[sigma * sigma, 0.0]] * 2), OverlapParams(max_rel_std=0.02))
    return bands[0], counts[0]


def detect_rows(rows, B):
    """Rows of signal (one image row each, in every channel) through the band detector:
    ``(image, weights, row_y, bands, counts)``, as :func:`measure_runs` takes them."""
    img = np.ascontiguousarray(np.repeat(np.asarray(rows, np.float64)[:, :, None], 3, 2))
    weights = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    b = BandParams()
    params = np.array([b.min_contrast, b.interval_tolerance, b.symmetry_tolerance_px,
                       b.min_gap_px, b.vertical_extra])  # fmt: skip
    row_y = np.arange(len(rows), dtype=np.int64)
    bands = np.empty((2, len(rows), 96, N_FIELDS))
    counts = np.empty((2, len(rows)), np.int64)
    detect_bands(img, weights, row_y, np.array([int(2 * B) | 1] * 2, np.int64), 255.0, params,
                 np.zeros((2, 3)), bands, counts)  # fmt: skip
    return img, weights, row_y, bands, counts


@pytest.mark.parametrize("B,w,sigma", RUN_SETS[:3])
def test_a_train_is_carried_to_rows_without_a_clean_gap(B, w, sigma):
    """Lines swept past their neighbours on a surface that ends (a clean gap, the floor)
    only in its first two rows: the rows below hold the train's pulses from edge to edge
    of the image, which alone pass for short bands a whole interval short (a depth
    tens of centimetres off, tuning rigs 4, 9 and 10).  Linked to the train measured in
    the rows above, they are its pulses: measured with its L / B as the reference for
    the integer part (within 0.5 %), or rejected, never valid and short.  (Where no
    train is measured next to the gap, they stay valid, as in a single row.)"""
    rows = [(0, 29)] * 2 + [(-12, 45)] * 6
    measured = 0
    for u in (1.25, 1.35, 1.65, 2.3):
        L = u * B
        bands, counts = detect_and_measure_rows(B, w, sigma, L, rows)
        if not np.any(bands[:2, :, F_VALID] == BAND_PERIODIC):
            continue  # no train measured next to the clean gap: the detector's limit
        for r in range(len(rows)):
            b = bands[r, : counts[r]]
            ok = b[:, F_VALID] > 0.0
            assert np.all(b[ok, F_VALID] == BAND_PERIODIC), (u, r)
            assert np.all(np.abs(b[ok, F_LENGTH] / L - 1.0) <= 0.005), (u, r)
            if r >= 2:
                measured += int(np.count_nonzero(ok))
    print(f"\nB={B}: pulses measured in the rows without a clean gap: {measured}")
    assert measured > 0


@pytest.mark.xfail(strict=True, reason="a train is carried onto another surface's bands as "
                   "long and high on its columns (known limit, see the docstring)")
def test_a_train_is_not_carried_onto_bands_of_their_own():
    """Below a train's rows (B 20 px, L 27 px), short bands of another surface (with clean
    gaps) that sit on its pulses' columns, as high and as long as its pulses.  They lie
    on their floor, not on the train's pedestal a pulse height up, but the train is
    carried onto them and they read one interval long (found in review).  Requiring the
    pedestal (or rejecting such bands) cost the tuning rigs more than it saved: rig 10's
    tilted board kept pulses a whole interval short (p90 7 -> 248 mm), rig 15's boards
    before a wall p90 13 -> 79 mm, rig 4's lost 14 points of coverage.  A known limit."""
    B, w, sigma, L, short = 20.0, 3.0, 1.0, 27.0, 5.0
    x0 = 0.5 * (L + w) + 30.0 + 0.3
    n = int(x0 + B * 29 + 0.5 * (L + w) + 30)
    reach = int(0.5 * (L + w) + 6 * sigma + 3)

    def row(length, amp, shift, lines):
        v = np.full(n, BG)
        for k in lines:
            ck = x0 + B * k + shift
            for j in range(max(0, int(ck) - reach), min(n, int(ck) + reach + 2)):
                v[j] += amp * pixel_value(j - ck, length, w, sigma)
        return v

    def detect(rows):
        return detect_rows(rows, B)

    train = row(L, 80.0, 0.0, range(30))
    # the train's pulses (n = 1: half-way between the lines) and their height
    _, _, _, tb, tc = detect([train])
    pulses = tb[0, 0, : tc[0, 0]]
    mid = pulses[3:-3]
    alone = row(short, 80.0, 0.5 * B, range(2, 27))
    _, _, _, ab, ac = detect([alone])
    scale = np.nanmedian(mid[:, F_HEIGHT]) / np.nanmedian(ab[0, 0, 2 : ac[0, 0] - 2, F_HEIGHT])
    others = row(short * np.nanmedian(mid[:, F_LENGTH]) / short, 80.0 * scale, 0.5 * B,
                 range(2, 27))  # fmt: skip
    img, weights, row_y, bands, counts = detect([train, train] + [others] * 4)
    own = bands[0, 2:, :, F_LENGTH].copy()
    measure_runs(img, weights, row_y, bands, counts, np.array([w, w]), np.array([B, B]),
                 np.array([[sigma * sigma, 0.0]] * 2), OverlapParams(max_rel_std=0.02))
    assert np.any(bands[0, :2, :, F_VALID] == BAND_PERIODIC)  # the train is measured
    for r in range(2, 6):
        b = bands[0, r, : counts[0, r]]
        assert not np.any(b[:, F_VALID] == BAND_PERIODIC), r
        valid = b[:, F_VALID] == 1.0
        # what stays valid keeps its own reading
        assert np.allclose(b[valid, F_LENGTH], own[r - 2, : counts[0, r]][valid]), r


def touching_rows(B, w, sigma, u0, u1, lines=60, n_rows=3, seed=2):
    """Rows covered by lines from edge to edge (no background at either end), whose sweep
    falls from ``u0`` to ``u1`` intervals along the row (a board moving along the axis:
    its bands touch on one side and stand apart on the other).  Returns the sweep of
    each line and the first pattern's bands after :func:`measure_runs`."""
    x0 = -2.0
    n = int(x0 + B * lines + 40)
    sweeps = np.linspace(u0, u1, lines) * B
    rng = np.random.default_rng(seed)
    img = np.empty((n_rows, n))
    for i in range(n_rows):
        v = np.full(n, BG)
        for k in range(lines):
            ck, L = x0 + B * k, sweeps[k]
            reach = int(0.5 * (L + w) + 6 * sigma + 3)
            for j in range(max(0, int(ck) - reach), min(n, int(ck) + reach + 2)):
                v[j] += 80.0 * pixel_value(j - ck, L, w, sigma)
        img[i] = v + rng.normal(0.0, 1.0, n)
    img, weights, row_y, bands, counts = detect_rows(img, B)
    measure_runs(img, weights, row_y, bands, counts, np.array([w, w]), np.array([B, B]),
                 np.array([[sigma * sigma, 0.0]] * 2), OverlapParams(max_rel_std=0.02))
    b = bands[0, 0, : counts[0, 0]]
    line = np.rint((b[:, F_CENTRE] - x0) / B)
    return sweeps, b, line


def test_touching_bands_without_a_floor_take_their_neighbours_sweep_as_reference():
    """Bands that touch over more than the floor's reach (8 intervals) show no clean gap:
    the floor gives no n for them.  The bands measured beside them in the row do, a run
    further per pass.  A long run measured as one stretch read -8 to +5 % at its ends:
    now its pieces take their own sweep where it differs (measured -2.1 to +1.2 %, a
    piece of 5 bands whose sweep changes along it), and the piece nearest an integer L / B
    (lines 1-5, 0.95-0.97 intervals), which cannot be measured, is rejected."""
    sweeps, b, line = touching_rows(25.0, 3.5, 0.9, 0.97, 0.6)
    per = b[:, F_VALID] == BAND_PERIODIC
    k = line[per].astype(int)
    err = b[per, F_LENGTH] / sweeps[k] - 1.0
    print(f"\nperiodic lines {k.tolist()}\nerrors % {np.round(100 * err, 1).tolist()}")
    assert set(range(6, 21)) <= set(k.tolist())
    assert np.all(np.abs(err) <= 0.03)
    # no band is valid and a whole interval short, and none reads its run's average alone
    ok = b[:, F_VALID] > 0
    assert np.all(np.abs(b[ok, F_LENGTH] / sweeps[line[ok].astype(int)] - 1.0) <= 0.03)
