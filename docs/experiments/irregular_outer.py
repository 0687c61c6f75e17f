"""Could the outermost bands of a ball's runs get their interval another way?

Reads what ``irregular_attribution.py --dump DIR`` wrote (see ``irregular-attribution.md``)
and prints, per case and pattern, against the renderer's true interval:

* ``loo``: outermost bands rejected as irregular (spacing changing too fast) whose
  extrapolation, linear or geometric, predicts the band's own spacing from the two
  beyond within 1, 2 or 4 % (a leave-one-out check): the interval it then extrapolates;
* ``limb``: the same bands' interval from a limb model of the line density,
  ``a + b / sqrt(x - x_limb)`` (lines bunch like the inverse square root of the distance
  to a sphere's limb), fitted exactly to the band's three spacings inward where a limb
  column beyond the band solves it;
* ``centres``: the true number of lines between two neighbouring band centres (the
  renderer's line density, 1 / interval, integrated between them) less one, for a pair
  with an outermost irregular band and for pairs of valid bands: whether the outermost
  bands' centres sit on their lines;
* ``rows``: every outermost irregular band and every valid inner band, the mean interval
  of the valid inner bands of the same line (centre within 0.3 interval) 1, 2 or 3
  measured rows above and below.

    .venv/bin/python docs/experiments/irregular_outer.py DIR
"""

from __future__ import annotations

import argparse
import glob
import pickle

import numpy as np

from lightflow.app.core import bands as bd

OUTER = -4.3  # the patch's code of an outermost band whose spacings change too fast


def stats(v) -> str:
    v = np.asarray(v, float)
    if not v.size:
        return "-"
    return (f"n {v.size} {100 * np.median(v):+.1f} % (|.| {100 * np.median(np.abs(v)):.1f}, "
            f"p90 {100 * np.quantile(np.abs(v), 0.9):.1f})")  # fmt: skip


def leave_one_out(path: str) -> None:
    with open(path, "rb") as f:
        recs = pickle.load(f)
    for p in range(2):
        for name in ("outermost, fast", "valid"):
            rs = [r for r in recs.get((p, name), []) if "res_lin" in r]
            if not rs:
                continue
            parts = []
            for th in (0.01, 0.02, 0.04):
                lin = [r["lin"] for r in rs if abs(r["res_lin"]) < th]
                geo = [r["geo"] for r in rs if abs(r["res_geo"]) < th]
                parts.append(f"within {100 * th:.0f} %: linear {stats(lin)}, "
                             f"geometric {stats(geo)}")
            print(f"  loo p{p} {name}: " + "; ".join(parts))


def _limb_interval(d1: float, d2: float, d3: float) -> float:
    """Interval at the outermost of four lines ``d1, d2, d3`` apart (going inward) under
    the limb model; NaN where no limb column beyond the band fits the three spacings."""
    x = np.array([0.0, d1, d1 + d2, d1 + d2 + d3])

    def solve(xl):
        # each spacing holds one line: a (x1 - x0) + 2 b (sqrt(x1 - xl) - sqrt(x0 - xl)) = 1
        a = np.array([[x[k + 1] - x[k], 2 * (np.sqrt(x[k + 1] - xl) - np.sqrt(x[k] - xl))]
                      for k in range(3)])  # fmt: skip
        ab = np.linalg.solve(a[:2], np.ones(2))
        return a[2] @ ab - 1, ab

    xs = -np.geomspace(1e-3 * d1, 1e3 * d1, 400)
    res = [solve(xl)[0] for xl in xs]
    for i in range(len(xs) - 1):
        if np.sign(res[i]) != np.sign(res[i + 1]):
            lo, hi = xs[i], xs[i + 1]
            for _ in range(50):
                m = 0.5 * (lo + hi)
                lo, hi = (m, hi) if np.sign(solve(m)[0]) == np.sign(solve(lo)[0]) else (lo, m)
            xl = 0.5 * (lo + hi)
            ab = solve(xl)[1]
            rho = ab[0] + ab[1] / np.sqrt(-xl)
            return 1 / rho if rho > 0 else np.nan
    return np.nan


def limb(path: str) -> None:
    with open(path, "rb") as f:
        recs = pickle.load(f)
    for p in range(2):
        rs = [r for r in recs.get((p, "outermost, fast"), []) if "d123" in r]
        err, lin = [], []
        for r in rs:
            d1, d2, _ = r["d123"]
            truth = (1.5 * d1 - 0.5 * d2) / (1 + r["lin"])
            iv = _limb_interval(*r["d123"])
            if np.isfinite(iv):
                err.append(iv / truth - 1)
                lin.append(r["lin"])
        print(f"  limb p{p} outermost, fast: {len(rs)} bands, fitted: {stats(err)}; "
              f"linear on those {stats(lin)}")


def inner(rb, q) -> bool:
    return (rb[q, bd.F_VALID] > 0 and 0 < q < len(rb) - 1 and np.isfinite(rb[q - 1, bd.F_CENTRE])
            and np.isfinite(rb[q + 1, bd.F_CENTRE]))  # fmt: skip


def from_rows(case: str) -> None:
    res = {}
    for f in sorted(glob.glob(case + "_*.npz")):
        z = np.load(f)
        bands, counts, row_y, truth = z["bands"], z["counts"], z["row_y"], z["interval"]
        for p in range(2):
            for r in range(len(row_y)):
                rb = bands[p, r, : counts[p, r]]
                for q, b in enumerate(rb):
                    c = b[bd.F_CENTRE]
                    outer = abs(b[bd.F_VALID] - OUTER) < 1e-6
                    if not (np.isfinite(c) and 0 <= c < truth.shape[2]) or not (
                            outer or inner(rb, q)):  # fmt: skip
                        continue
                    ti = truth[p, row_y[r], int(round(c))]
                    if not np.isfinite(ti):
                        continue
                    d = res.setdefault((p, "outer" if outer else "inner"),
                                       {"own": [], 1: [], 2: [], 3: []})  # fmt: skip
                    if not outer:
                        d["own"].append(b[bd.F_INTERVAL] / ti - 1)
                    for dr in (1, 2, 3):
                        vals = []
                        for rr in (r - dr, r + dr):
                            if 0 <= rr < len(row_y):
                                ob = bands[p, rr, : counts[p, rr]]
                                vals += [o[bd.F_INTERVAL] for qq, o in enumerate(ob)
                                         if inner(ob, qq)
                                         and abs(o[bd.F_CENTRE] - c) < 0.3 * o[bd.F_INTERVAL]]
                        if vals:
                            d[dr].append(np.mean(vals) / ti - 1)
    for (p, key), d in sorted(res.items()):
        print(f"  rows p{p} {key}: own {stats(d['own'])}; rows +-1 {stats(d[1])}; "
              f"+-2 {stats(d[2])}; +-3 {stats(d[3])}")


def centres(case: str) -> None:
    res = {}
    for f in sorted(glob.glob(case + "_*.npz")):
        z = np.load(f)
        bands, counts, row_y, truth = z["bands"], z["counts"], z["row_y"], z["interval"]
        for p in range(2):
            for r in range(len(row_y)):
                rb = bands[p, r, : counts[p, r]]
                density = 1.0 / truth[p, row_y[r]]
                for q in range(len(rb) - 1):
                    c0, c1 = rb[q, bd.F_CENTRE], rb[q + 1, bd.F_CENTRE]
                    w = len(density)
                    if not (np.isfinite(c0) and np.isfinite(c1)) or c0 < 0 or c1 >= w - 1:
                        continue
                    xs = np.arange(int(np.ceil(c0)), int(np.floor(c1)) + 1)
                    v = density[xs]
                    if len(xs) < 3 or not np.isfinite(v).all():
                        continue
                    n = np.trapezoid(v, xs) + (xs[0] - c0) * v[0] + (c1 - xs[-1]) * v[-1]
                    codes = rb[q : q + 2, bd.F_VALID]
                    if (np.abs(codes - OUTER) < 1e-6).any():
                        res.setdefault((p, "outermost pair"), []).append(n - 1)
                    elif (codes > 0).all():
                        res.setdefault((p, "valid pair"), []).append(n - 1)
    for (p, key), v in sorted(res.items()):
        print(f"  centres p{p} {key}: lines between - 1 {stats(v)}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dump", help="the --dump folder of irregular_attribution.py")
    args = ap.parse_args()
    for path in sorted(glob.glob(f"{args.dump}/*.pkl")):
        case = path[: -len(".pkl")]
        print("==", case.rsplit("/", 1)[-1])
        leave_one_out(path)
        limb(path)
        from_rows(case)
        centres(case)


if __name__ == "__main__":
    main()
