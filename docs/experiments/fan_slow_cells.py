"""Why a fan's slow cells read static: the band readings there against the renderer's truth.

Fourteenth session, issue 8 (see fan-slow-cells.md beside this file).  For one case of an
evaluation-matrix folder, per pattern and per class of grid cell (on the fan and "static",
on the fan with a depth, on the wall behind it), prints how the measured band width ``m``
and ramp ``r`` differ from the profile model at the true sweep and line width, and how
far the line width the pipeline derives from the measured interval is from the truth::

    python docs/experiments/fan_slow_cells.py /tmp/lead-eval gen1 gen1-fan-1ms-1ms

(the matrix folder from ``lightflow eval --matrix DIR --tuning-rigs``, which also holds
``<rig>-blur``, the blur calibration recording).
"""

from __future__ import annotations

import sys

import numpy as np

from lightflow.app.blurcal import calibrate_optics
from lightflow.app.core import causes as cz
from lightflow.app.core import flow as flow_module
from lightflow.app.core.pipeline import DepthPipeline, PipelineConfig
from lightflow.app.core.profile_model import tables
from lightflow.app.evaluation import read_scene_info
from lightflow.app.recording import read_recording, recording_frames
from lightflow.app.stages import true_flows
from lightflow.drivers.sim.scenes import get_scene
from lightflow.drivers.sim.synthetic import SceneRenderer


def main(matrix: str, rig_name: str, case: str) -> None:
    seen = {}
    combine = flow_module.FlowModel.combine

    def spy(self, grids, params, *args, **kwargs):
        seen["grids"], seen["model"] = grids.copy(), self
        return combine(self, grids, params, *args, **kwargs)

    flow_module.FlowModel.combine = spy
    rec = read_recording(f"{matrix}/{case}")
    blur = recording_frames(read_recording(f"{matrix}/{rig_name}-blur"))
    rig = calibrate_optics(rec.rig, blur)[0]
    scene = get_scene(str(read_scene_info(f"{matrix}/{case}").get("scene")))
    renderer = SceneRenderer(rec.rig, scene)
    frame = next(iter(recording_frames(rec)))
    result = DepthPipeline(rig, PipelineConfig()).process(frame)
    grids, model = seen["grids"], seen["model"]
    truth = true_flows(renderer, frame.timestamp, frame.exposure_s)
    s = result.stride
    gh, gw = result.causes_grid.shape
    ys = (np.arange(gh) * s + (s - 1) // 2)[:, None]
    xs = (np.arange(gw) * s + (s - 1) // 2)[None]
    ids = np.load(f"{matrix}/{case}/ground_truth/000000.npz")["object_id"][ys, xs]
    tab = tables()
    classes = (
        ("fan, static", (ids >= 2) & (result.causes_grid == cz.STATIC)),
        ("fan, depth", (ids >= 2) & (result.causes_grid == cz.DEPTH)),
        ("wall", ids == 1),
    )
    for name, cells in classes:
        for p in range(2):
            m, interval, ramp, slant = grids[p, 0], grids[p, 1], grids[p, 2], grids[p, 3]
            scale = interval / rig.patterns[p][1].pitch_px
            line = model.line_px[p] * scale
            sigma = np.sqrt(model.blur[p, 0] * (1 + np.nan_to_num(slant) ** 2)
                            + model.blur[p, 1] * scale**2)  # fmt: skip
            wall = name == "wall"
            sweep = np.zeros_like(m) if wall else np.nan_to_num(truth.sweep[p][ys, xs])
            width = line if wall else truth.line[p][ys, xs]
            sel = cells & np.isfinite(m) & np.isfinite(ramp) & np.isfinite(width)
            m_true = tab.measured_width(sweep[sel], width[sel], sigma[sel])
            r_true = tab.ramp(sweep[sel], width[sel], sigma[sel])
            m_line = tab.measured_width(sweep[sel], line[sel], sigma[sel])
            read = tab.joint_length(m[sel], ramp[sel], line[sel], sigma[sel])
            print(f"{name:12s} pattern {p}: {sel.sum():5d} cells; true sweep "
                  f"{np.median(sweep[sel]):.2f} px, read {np.nanmedian(read):.2f}; "
                  f"m - m(true L, true w) {np.median(m[sel] - m_true):+.3f} px, "
                  f"m - m(true L, w from interval) {np.median(m[sel] - m_line):+.3f} px, "
                  f"r - r(true L, true w) {np.median(ramp[sel] - r_true):+.3f} px; "
                  f"line from interval {100 * np.median(line[sel] / width[sel] - 1):+.2f} %")


if __name__ == "__main__":
    main(*sys.argv[1:4])
