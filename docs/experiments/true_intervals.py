"""Score a rendered case with the renderer's true line intervals put into the pipeline's grid.

An experiment, not part of the pipeline (see ``ball-interval-attribution.md`` beside it):
it replaces the measured interval of each grid cell that has one by the renderer's
(:func:`lightflow.app.stages.true_flows`) before the flows are read, so that what is
left of a depth error is what the intervals do not explain.  The blur is calibrated
as ``lightflow eval --matrix`` does, on the rig's rendered ``<rig>-blur`` recording.

    .venv/bin/python docs/experiments/true_intervals.py /tmp/eval gen1 \
        gen1-ball-toward-5ms --patterns 1 --region interp
"""

from __future__ import annotations

import argparse

import numpy as np

from lightflow.app.blurcal import calibrate_optics
from lightflow.app.core import bands as bd
from lightflow.app.core import pipeline as pl
from lightflow.app.evaluation import evaluate_recording, read_scene_info
from lightflow.app.recording import read_recording, recording_frames
from lightflow.app.stages import format_stages, true_flows
from lightflow.drivers.sim.scenes import get_scene
from lightflow.drivers.sim.synthetic import SceneRenderer


def interpolated_cells(bands, counts, rows_per_cell, stride, shape) -> np.ndarray:
    """Per pattern, the grid cells between two valid bands of a run (not extrapolated)."""
    gh, gw = shape
    off = 0.5 * (stride - 1)
    out = np.zeros((2, gh, gw), bool)
    for p in range(2):
        for r in range(counts.shape[1]):
            b = bands[p, r, : counts[p, r]]
            valid = [j for j in range(len(b))
                     if b[j, bd.F_VALID] > 0 and np.isfinite(b[j, bd.F_CENTRE])]  # fmt: skip
            for j0, j1 in zip(valid[:-1], valid[1:], strict=True):
                c0, c1 = b[j0, bd.F_CENTRE], b[j1, bd.F_CENTRE]
                if 0 < c1 - c0 <= 1.6 * max(b[j0, bd.F_INTERVAL], b[j1, bd.F_INTERVAL]):
                    a = max(int(np.ceil((c0 - off) / stride)), 0)
                    e = min(int(np.floor((c1 - off) / stride)), gw - 1)
                    out[p, r // rows_per_cell, a : e + 1] = True
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("matrix", help="the --matrix folder of a lightflow eval run")
    ap.add_argument("rig", help="rig name of the cases (its <rig>-blur recording calibrates)")
    ap.add_argument("cases", nargs="+")
    ap.add_argument("--patterns", default="01", help="patterns whose intervals are replaced")
    ap.add_argument("--region", choices=("all", "interp", "extrap"), default="all",
                    help="cells between two bands of a run, or beyond its ends")  # fmt: skip
    args = ap.parse_args()
    pats = [int(c) for c in args.patterns]
    first = read_recording(f"{args.matrix}/{args.cases[0]}")
    blur = recording_frames(read_recording(f"{args.matrix}/{args.rig}-blur"))
    rig, _, _ = calibrate_optics(first.rig, blur)
    measure = pl.DepthPipeline._measure
    state = {}

    def replaced(self, frame, timings, buffers=None):
        bands, counts, grids = measure(self, frame, timings, buffers)
        flows = true_flows(state["renderer"], frame.timestamp, frame.exposure_s)
        s = self.config.stride
        gh, gw = grids.shape[-2:]
        cells = np.ix_(np.arange(gh) * s + (s - 1) // 2, np.arange(gw) * s + (s - 1) // 2)
        inner = interpolated_cells(bands, counts, self._rows_per_cell, s, (gh, gw))
        for p in pats:
            truth = flows.interval[p][cells]
            ok = np.isfinite(grids[p, 1]) & np.isfinite(truth)
            if args.region != "all":
                ok &= inner[p] if args.region == "interp" else ~inner[p]
            grids[p, 1][ok] = truth[ok]
        return bands, counts, grids

    pl.DepthPipeline._measure = replaced
    for case in args.cases:
        path = f"{args.matrix}/{case}"
        scene = get_scene(str(read_scene_info(path).get("scene")))
        state["renderer"] = SceneRenderer(read_recording(path, rig).rig, scene)
        m = evaluate_recording(path, rig=rig, stages=True)
        print(f"{case}, true intervals of patterns {pats} ({args.region}): median "
              f"{1e3 * m.median_error_m:.1f} mm, signed {1e3 * m.median_signed_m:+.1f} mm, "
              f"coverage {100 * m.coverage:.0f} %")  # fmt: skip
        print("   ", format_stages(case, m.stages))


if __name__ == "__main__":
    main()
