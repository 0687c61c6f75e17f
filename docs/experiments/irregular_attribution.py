"""Which check made a ball's bands *irregular*, and would they have measured right?

An experiment, not part of the pipeline (see ``irregular-attribution.md`` beside it).
Needs ``irregular-reasons.patch`` applied: the band detector then leaves a sub-code
per irregular check (-4.1 a dip inside the band, -4.2 no neighbour centre, -4.3 the
outermost band of a run whose spacings change too fast, -4.4 spacings on the two sides
that disagree with neither a consistent side nor a smooth trend, -4.5 neighbour heights
outside 0.4-2.5x); ``LF_KEEP_IRR`` (a bitmask 1, 2, 4, 8, 16 in that order) keeps the
bands of those checks valid instead (with a fresh ``NUMBA_CACHE_DIR``: numba freezes it).

Per case it prints, on the moving object (the renderer's true sweep finite in both
patterns), the grid pixels whose cause is *irregular* by the check that made their
band so, and per check and pattern the bands on the object: how many, their interval
against the renderer's (the one the detector computed, and a geometric extrapolation
for the outermost bands), their length against ``max(true sweep, true line width)``
(the half-height width of a swept line, without blur) and their neighbours' height
ratios; valid bands alike for comparison.

    git apply docs/experiments/irregular-reasons.patch
    .venv/bin/python docs/experiments/irregular_attribution.py /tmp/irr-eval gen1 \
        gen1-ball-toward-5ms [--dump DIR]
    git apply -R docs/experiments/irregular-reasons.patch

``--dump DIR`` also writes each case's band records (``<case>.pkl``) and each frame's
band table with the true intervals and sweeps (``<case>_<frame>.npz``), which
``irregular_outer.py`` reads.
"""

from __future__ import annotations

import argparse
import math
import pickle
from collections import defaultdict

import numpy as np

from lightflow.app.blurcal import calibrate_optics
from lightflow.app.core import bands as bd
from lightflow.app.core import causes as cz
from lightflow.app.core import pipeline as pl
from lightflow.app.evaluation import evaluate_recording, read_scene_info
from lightflow.app.recording import read_recording, recording_frames
from lightflow.app.stages import true_flows
from lightflow.drivers.sim.scenes import get_scene
from lightflow.drivers.sim.synthetic import SceneRenderer

REASONS = {-4.1: "dip", -4.2: "no neighbour", -4.3: "outermost, fast", -4.4: "sides disagree",
           -4.5: "heights", 1.0: "valid", 2.0: "valid (periodic)"}  # fmt: skip


def reason(code: float) -> str:
    for c, name in REASONS.items():
        if abs(code - c) < 1e-6:
            return name
    return "other"


def geo_interval(d1: float, d2: float) -> float:
    """Interval at the outer band from its spacing d1 and the next one d2 (geometric)."""
    q = d2 / d1
    return d1 if abs(q - 1) < 1e-9 else d1 * math.log(q) / (q - 1)


def nearest(row_bands: np.ndarray, x: float) -> int:
    best, bi = np.inf, -1
    for q, b in enumerate(row_bands):
        ramp = b[bd.F_RAMP] if b[bd.F_RAMP] > 0 else 0.0
        a, e = b[bd.F_START] - 2 * ramp, b[bd.F_END] + 2 * ramp
        d = a - x if x < a else (x - e if x > e else 0.0)
        if d <= best:
            best, bi = d, q
    return bi


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("matrix")
    ap.add_argument("rig")
    ap.add_argument("cases", nargs="+")
    ap.add_argument("--dump", help="folder to pickle the band records into")
    args = ap.parse_args()
    first = read_recording(f"{args.matrix}/{args.cases[0]}")
    blur = recording_frames(read_recording(f"{args.matrix}/{args.rig}-blur"))
    rig, _, _ = calibrate_optics(first.rig, blur)
    measure = pl.DepthPipeline._measure
    process = pl.DepthPipeline.process
    state = {}

    def measured(self, frame, timings, buffers=None):
        bands, counts, grids = measure(self, frame, timings, buffers)
        state["last"] = (bands.copy(), counts.copy(), grids.copy())
        return bands, counts, grids

    def processed(self, frame):
        res = process(self, frame)
        bands, counts, grids = state["last"]
        tf = true_flows(state["renderer"], frame.timestamp, frame.exposure_s)
        s = self.config.stride
        k = self._rows_per_cell
        gh, gw = res.causes_grid.shape
        ys = np.arange(gh) * s + (s - 1) // 2
        xs = np.arange(gw) * s + (s - 1) // 2
        moving = np.isfinite(tf.sweep[:, ys][:, :, xs]).all(axis=0)
        px = state["px"]
        irr = moving & (res.causes_grid == cz.IRREGULAR)
        px["moving"] += int(moving.sum())
        px["irregular"] += int(irr.sum())
        for i, j in zip(*np.nonzero(irr), strict=True):
            r = i * k
            why = None
            for p in range(2):
                if np.isfinite(grids[p, 1, i, j]):
                    continue
                rb = bands[p, r, : counts[p, r]]
                q = nearest(rb, xs[j])
                if q >= 0 and rb[q, bd.F_VALID] < -4.0 + 1e-6 and rb[q, bd.F_VALID] > -5:
                    why = (p, reason(rb[q, bd.F_VALID]))
                    break
            px[why or (None, "?")] += 1
        if state.get("dump"):
            state["frame"] = state.get("frame", 0) + 1
            np.savez_compressed(f"{state['dump']}_{state['frame']}.npz", bands=bands,
                                counts=counts, row_y=self._row_y, interval=tf.interval,
                                sweep=tf.sweep)  # fmt: skip
        # band level: every measured band on the moving object
        rows = state["bands"]
        h, w = tf.sweep.shape[1:]
        for p in range(2):
            for r, y in enumerate(self._row_y):
                rb = bands[p, r, : counts[p, r]]
                cs = rb[:, bd.F_CENTRE]
                for q, b in enumerate(rb):
                    c = b[bd.F_CENTRE]
                    if not np.isfinite(c) or not 0 <= c < w:
                        continue
                    x = int(round(c))
                    ts, ti, tl = (float(m[p, y, x]) for m in (tf.sweep, tf.interval, tf.line))
                    if not (np.isfinite(ts) and np.isfinite(ti)):
                        continue
                    name = reason(b[bd.F_VALID])
                    if name == "other":
                        continue
                    rec = {"iv": b[bd.F_INTERVAL] / ti - 1, "len": b[bd.F_LENGTH] / max(ts, tl) - 1,
                           "sw": ts / tl}  # fmt: skip
                    # the outermost band: geometric extrapolation of its one side
                    left = q > 0 and np.isfinite(cs[q - 1])
                    right = q + 1 < len(rb) and np.isfinite(cs[q + 1])
                    if left != right:
                        sg = -1 if left else 1
                        if 0 <= q + 2 * sg < len(rb) and np.isfinite(cs[q + 2 * sg]):
                            d1 = abs(cs[q + sg] - c)
                            d2 = abs(cs[q + 2 * sg] - cs[q + sg])
                            if d1 > 2 and d2 > 2:
                                rec["geo"] = geo_interval(d1, d2) / ti - 1
                                rec["lin"] = (1.5 * d1 - 0.5 * d2) / ti - 1
                                # the density 1 / spacing, linear through the two spacings'
                                # middles, at the band
                                m1, m2 = c + sg * 0.5 * d1, c + sg * (d1 + 0.5 * d2)
                                rho = 1 / d1 + (1 / d2 - 1 / d1) * (c - m1) / (m2 - m1)
                                rec["dlin"] = 1 / rho / ti - 1 if rho > 0 else np.nan
                                if 0 <= q + 3 * sg < len(rb) and np.isfinite(cs[q + 3 * sg]):
                                    d3 = abs(cs[q + 3 * sg] - cs[q + 2 * sg])
                                    # how well each model predicts the band's own spacing from
                                    # the two beyond (a leave-one-out check of the extrapolation)
                                    rec["res_lin"] = (2 * d2 - d3) / d1 - 1
                                    rec["res_geo"] = d2 * d2 / d3 / d1 - 1
                                    rec["d123"] = (d1, d2, d3)
                                    xs4 = sorted([c, cs[q + sg], cs[q + 2 * sg], cs[q + 3 * sg]])
                                    if min(np.diff(xs4)) > 2:
                                        rho = bd._density_at(*xs4, c)
                                        rec["dquad"] = 1 / rho / ti - 1 if rho > 0 else np.nan
                    if left and right:
                        # the density interpolated quadratically from four lines, as
                        # _trend_interval has it, averaged over both sides' fourth lines
                        acc = []
                        for x4 in ((q - 2, q - 1, q, q + 1), (q - 1, q, q + 1, q + 2)):
                            if x4[0] >= 0 and x4[3] < len(rb) and np.isfinite(cs[list(x4)]).all():
                                xs4 = cs[list(x4)]
                                if min(np.diff(xs4)) > 2:
                                    acc.append(1 / bd._density_at(*xs4, c))
                        if acc:
                            rec["dq2"] = np.mean(acc) / ti - 1
                        d1, d2 = c - cs[q - 1], cs[q + 1] - c
                        rec["dmin"] = min(d1, d2) / ti - 1
                        rec["dmax"] = max(d1, d2) / ti - 1
                        rec["dr"] = max(d1, d2) / min(d1, d2) - 1
                        itol = bd.BandParams().interval_tolerance
                        sides = []
                        for k1, k2 in ((q - 1, q - 2), (q + 1, q + 2)):
                            iv = np.nan
                            if 0 <= k2 < len(rb):
                                e1, e2 = abs(cs[k1] - c), abs(cs[k2] - cs[k1])
                                if e1 > 2 and e2 > 2:
                                    iv = 1.5 * e1 - 0.5 * e2
                                    if abs(e1 - e2) > 0.5 * itol * iv:
                                        iv = np.nan
                            sides.append(iv)
                        rec["nsides"] = float(np.isfinite(sides).sum())
                        # the side whose next band's length is nearer the band's own
                        ln = b[bd.F_LENGTH]
                        el = abs(rb[q - 1, bd.F_LENGTH] - ln)
                        near = 0 if el < abs(rb[q + 1, bd.F_LENGTH] - ln) else 1
                        rec["samelen"] = (d1 if near == 0 else d2) / ti - 1
                        if np.isfinite(sides[near]):
                            rec["samelen_side"] = sides[near] / ti - 1
                        h0 = b[bd.F_HEIGHT]
                        rec["hr"] = max(rb[q - 1, bd.F_HEIGHT] / h0, rb[q + 1, bd.F_HEIGHT] / h0,
                                        h0 / rb[q - 1, bd.F_HEIGHT], h0 / rb[q + 1, bd.F_HEIGHT])
                    rows[(p, name)].append(rec)
        return res

    pl.DepthPipeline._measure = measured
    pl.DepthPipeline.process = processed
    for case in args.cases:
        path = f"{args.matrix}/{case}"
        scene = get_scene(str(read_scene_info(path).get("scene")))
        state["renderer"] = SceneRenderer(read_recording(path, rig).rig, scene)
        state["px"] = defaultdict(int)
        state["bands"] = defaultdict(list)
        state["dump"] = f"{args.dump}/{case}" if args.dump else None
        state["frame"] = 0
        m = evaluate_recording(path, rig=rig)
        if args.dump:
            with open(f"{args.dump}/{case}.pkl", "wb") as f:
                pickle.dump(dict(state["bands"]), f)
        px = state["px"]
        print(f"== {case}: median {1e3 * m.median_error_m:.1f} mm, signed "
              f"{1e3 * m.median_signed_m:+.1f} mm, coverage {100 * m.coverage:.0f} %")
        mv = max(px["moving"], 1)
        print(f"  moving grid px {px['moving']}, irregular {px['irregular']} "
              f"({100 * px['irregular'] / mv:.0f} %)")
        for key, n in sorted(px.items(), key=lambda kv: -kv[1] if isinstance(kv[0], tuple) else 0):
            if isinstance(key, tuple):
                print(f"    pattern {key[0]} {key[1]}: {n} px ({100 * n / mv:.1f} % of moving)")
        for (p, name), recs in sorted(state["bands"].items()):
            def med(f, recs=recs):
                v = np.array([r[f] for r in recs if f in r and np.isfinite(r[f])])
                if not v.size:
                    return "-"
                return (f"{100 * np.median(v):+.1f} % (|.| {100 * np.median(np.abs(v)):.1f}, "
                        f"p90 {100 * np.quantile(np.abs(v), 0.9):.1f}; n {v.size})")
            hr = np.array([r["hr"] for r in recs if "hr" in r and np.isfinite(r["hr"])])
            swl = np.median([r["sw"] for r in recs])
            print(f"  p{p} {name}: {len(recs)} bands, true sweep/line {swl:.2f}; interval "
                  f"{med('iv')}; length {med('len')}; outer lin {med('lin')}, geo {med('geo')}, "
                  f"density lin {med('dlin')}, quad {med('dquad')}, two-sided quad {med('dq2')}, "
                  f"smaller spacing {med('dmin')}, larger {med('dmax')}, ratio-1 {med('dr')}, "
                  f"sides consistent {med('nsides')}, nearer length's spacing {med('samelen')}, "
                  f"its side {med('samelen_side')}; "
                  f"height ratio >2.5: {np.mean(hr > 2.5) * 100 if hr.size else 0:.0f} %")


if __name__ == "__main__":
    main()
