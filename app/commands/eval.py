"""``lightflow eval REC...``: depth accuracy on simulated recordings, and error vs exposure."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from lightflow.app.core.errors import ConfigError
from lightflow.app.options import STRIDES

DESCRIPTION = """\
Replay simulated recordings (written by `lightflow simulate`, which stores the
ground truth in REC/ground_truth/) through the depth pipeline, every frame in
order, and compare the depth with the truth:

  coverage    moving pixels lit by every projector that got a depth
  median/p90  absolute depth error on the moving object (mm)
  signed      median of estimate minus truth (a bias shows here)
  2 cm off    share of the depth on the moving object 2 cm off or more: a
              wrong line or a flow far off, which the median and even the
              90th percentile hide while it is under one pixel in ten
  plane RMSE  planar scenes: RMSE of the estimate's 3D points from a robustly
              fitted plane (the paper's metric, mm)
  off-object  share of the depth pixels that are not on a moving object
  within 1σ   share of the depths whose error is within one (two) predicted
  (2σ)        standard deviations (OUT/<frame>_std.npy): about 68 % (95 %)
              when the prediction is right
The matrix also lists, per case, the largest causes of "no depth" on the
moving object (static, irregular, cut, uncertain, ...).

With several recordings (e.g. one scene at several --exposure values), also
draws the median error and plane RMSE against exposure as a PNG, like the
paper's RMSE-against-shutter-speed plot.

`--matrix DIR` instead runs the evaluation matrix (`make eval`): seeded,
generated two-projector rigs (one projector in front of the camera plane,
toe-in 15-35 degrees, pitches 16-40 px, one with lens distortion) and the
single-projector rig, the paper's scenes at its exposures (fan 1 ms, balls 5
and 8 ms, boards 300 ms) and our faster boards at 20 ms.  The rigs it
reports were never used to choose defaults (--tuning-rigs shows those);
--seeds draws fresh ones, e.g. `--seeds 19-24`, to check that they carry over.

Example:
  for e in 0.005 0.01 0.02 0.03; do
    lightflow simulate --scene board --exposure $e --frames 5 --out rec-$e
  done
  lightflow eval rec-* --plot error-vs-exposure.png"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "eval",
        help="score the depth pipeline on simulated recordings (with ground truth)",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "recordings", nargs="*", type=Path, metavar="REC", help="simulated recording folder(s)"
    )
    p.add_argument("--matrix", type=Path, metavar="DIR",
                   help="run the evaluation matrix (generated rigs x every scene x the paper's "
                   "exposures), keeping its recordings in DIR; prints a markdown table and "
                   "writes DIR/matrix.md and DIR/matrix.json")
    p.add_argument("--frames", type=int, default=2, metavar="N",
                   help="--matrix: frames per case (default 2)")
    p.add_argument("--no-blur-calibration", action="store_true",
                   help="--matrix: score every rig without first measuring its blur on a "
                   "board held still at three depths (`lightflow rig blur`); the pipeline then "
                   "fits the blur on the moving bands of each recording")
    p.add_argument("--case", action="append", default=[], metavar="PATTERN",
                   help="--matrix: run only the cases whose name matches this shell pattern "
                   "(repeatable), e.g. 'gen2026+gamma2.2-*'; the table then lists those only")
    p.add_argument("--tuning-rigs", action="store_true",
                   help="--matrix: use the rigs defaults were developed on instead of the "
                   "reported ones")
    p.add_argument("--seeds", default="", metavar="LIST",
                   help="--matrix: draw the two-projector rigs from these generator seeds "
                   "instead (e.g. 19-24 or 19,21,30; the last one gets lens distortion), to "
                   "check that the defaults carry over to rigs nobody has looked at (1-18 "
                   "were)")
    p.add_argument(
        "--plot",
        type=Path,
        metavar="FILE.png",
        help="error-against-exposure plot (default with several recordings: eval.png)",
    )
    p.add_argument(
        "--stride",
        type=int,
        default=None,
        choices=STRIDES,
        help="analysis grid stride of the pipeline (default: the pipeline's)",
    )
    p.add_argument(
        "--arc-recheck", choices=("on", "off"), default="off",
        help="score the pipeline with `replay --arc-recheck on` (default: off, the "
        "pipeline's default)",
    )
    p.add_argument("--stages", action="store_true",
                   help="also trace the error to its stage: each pattern's flow against the "
                   "renderer's true flows (from `simulate --truth-flows`, or computed from "
                   "the scene), the log ratio and the depth")
    p.add_argument("--json", type=Path, metavar="FILE", help="also write the metrics as JSON")
    p.add_argument("--pictures", type=Path, metavar="DIR",
                   help="also draw each recording's (case's) last frame into DIR/<name>.png: "
                   "the camera image, the signed depth error, and why the moving object got no "
                   "depth, cause by cause")
    p.add_argument("--rig", metavar="RIG", help="rig file overriding the recordings' embedded rig")
    p.set_defaults(func=run)


def _progress(name: str):
    def report(stage: str, i: int, n: int) -> None:
        end = "\n" if i == n else ""
        print(f"\r{name}: {stage} {i}/{n}", end=end, file=sys.stderr, flush=True)

    return report


def _mm(v: float, digits: int = 1) -> str:
    return "-" if not math.isfinite(v) else f"{v * 1e3:.{digits}f}"


def _pct(v: float) -> str:
    return "-" if not math.isfinite(v) else f"{v * 100:.1f}"


def format_table(metrics) -> list[str]:
    """The metrics of several recordings as aligned text lines."""
    head = ("recording", "scene", "exposure ms", "frames", "coverage %", "median mm",
            "signed mm", "p90 mm", "2 cm off %", "plane RMSE mm", "off-object %",
            "within 1σ %", "within 2σ %")  # fmt: skip
    rows = [
        (m.path, m.scene, f"{m.exposure_s * 1e3:g}", str(m.frames), _pct(m.coverage),
         _mm(m.median_error_m), _mm(m.median_signed_m), _mm(m.p90_error_m), _pct(m.gross),
         _mm(m.plane_rmse_m), _pct(m.off_object), _pct(m.within_1sigma),
         _pct(m.within_2sigma))
        for m in metrics
    ]  # fmt: skip
    widths = [max(len(r[i]) for r in [head, *rows]) for i in range(len(head))]

    def line(cells):
        # names left-aligned, numbers right-aligned
        pairs = enumerate(zip(cells, widths, strict=True))
        return "  ".join(c.ljust(w) if i < 2 else c.rjust(w) for i, (c, w) in pairs).rstrip()

    return [line(head), "  ".join("-" * w for w in widths), *(line(r) for r in rows)]


def plot_error_vs_exposure(metrics, path: Path) -> None:
    """Median error and plane RMSE (mm) against exposure (ms), one pair of lines per scene."""
    from lightflow.app.plot import Series, line_plot, save_png

    series = []
    for scene in dict.fromkeys(m.scene for m in metrics):
        ms = sorted((m for m in metrics if m.scene == scene), key=lambda m: m.exposure_s)
        x = tuple(m.exposure_s * 1e3 for m in ms)
        series.append(
            Series(f"median error ({scene})", x, tuple(m.median_error_m * 1e3 for m in ms))
        )
        if any(m.planar for m in ms):
            series.append(
                Series(f"plane RMSE ({scene})", x, tuple(m.plane_rmse_m * 1e3 for m in ms))
            )
    img = line_plot(
        series,
        title="Depth error against exposure (synthetic ground truth)",
        xlabel="exposure (ms)",
        ylabel="error (mm)",
    )
    save_png(img, path)


def run(args: argparse.Namespace) -> int:
    from lightflow.app.core.pipeline import PipelineConfig
    from lightflow.app.core.rig import resolve_rig
    from lightflow.app.evaluation import evaluate_recording, require_truth, write_metrics_json
    from lightflow.app.recording import read_recording

    if args.matrix is not None:
        return _run_matrix(args)
    if args.seeds:
        raise ConfigError("--seeds: only with --matrix DIR")
    if not args.recordings:
        raise ConfigError("eval: give recording folders, or --matrix DIR")
    rig = resolve_rig(args.rig) if args.rig else None
    # check every recording before the long replays, so a typo fails at once
    for rec in args.recordings:
        read_recording(rec, rig)
        require_truth(rec)
    if args.plot is not None and args.plot.suffix.lower() != ".png":
        raise ConfigError(f"--plot {args.plot}: expected a .png file name")
    config = _config(args) or PipelineConfig()
    pictures = _pictures_dir(args.pictures)
    results = []
    for rec in args.recordings:
        picture = None if pictures is None else pictures / f"{Path(rec).resolve().name}.png"
        results.append(evaluate_recording(rec, rig, config, progress=_progress(str(rec)),
                                          stages=args.stages, picture=picture))  # fmt: skip
    for line in format_table(results):
        print(line)
    if args.stages:
        _print_stages([(str(m.path), m) for m in results])
    if args.json is not None:
        write_metrics_json(results, args.json)
        print(f"metrics written to {args.json}")
    if pictures is not None:
        print(f"pictures written to {pictures}/")
    plot = args.plot or (Path("eval.png") if len(results) > 1 else None)
    if plot is not None:
        plot_error_vs_exposure(results, plot)
        print(f"plot written to {plot}")
    return 0


def _pictures_dir(path: Path | None) -> Path | None:
    """``--pictures DIR``, created; a ConfigError names it when it cannot be."""
    if path is None:
        return None
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"--pictures {path}: cannot create the folder ({exc.strerror})") from None
    return path


def _print_stages(named) -> None:
    from lightflow.app.stages import format_stages

    print("\nwhere the error comes from (moving pixels with depth; flows against the "
          "renderer's truth):")  # fmt: skip
    for name, m in named:
        if m.stages:
            print("  " + format_stages(name, m.stages))


def _seed_list(text: str) -> tuple[int, ...]:
    """``7-12`` or ``3,5,9`` (or both, comma-separated) as a tuple of seeds."""
    seeds: list[int] = []
    try:
        for part in text.split(","):
            a, dash, b = part.strip().partition("-")
            lo, hi = int(a), int(b if dash else a)
            if hi < lo:
                raise ValueError
            seeds.extend(range(lo, hi + 1))
    except ValueError:
        raise ConfigError(f"--seeds: expected seeds like 19-24 or 19,21,30, got {text!r}"
                          ) from None  # fmt: skip
    if len(set(seeds)) != len(seeds):
        raise ConfigError(f"--seeds: {text!r} names a seed twice")
    return tuple(seeds)


def _run_matrix(args: argparse.Namespace) -> int:
    import json

    from lightflow.app.eval_matrix import format_matrix, run_matrix

    if args.frames < 1:
        raise ConfigError(f"--frames: expected at least 1, got {args.frames}")
    seeds = _seed_list(args.seeds) if args.seeds else ()
    if seeds and args.tuning_rigs:
        raise ConfigError("--seeds and --tuning-rigs: give one of them")
    out = args.matrix
    out.mkdir(parents=True, exist_ok=True)

    def progress(stage: str, i: int, n: int) -> None:
        print(f"\r  {stage} {i}/{n}", end="\n" if i == n else "", file=sys.stderr, flush=True)

    pictures = _pictures_dir(args.pictures)
    config = _config(args)
    results = run_matrix(out, frames=args.frames, tuning=args.tuning_rigs, seeds=seeds,
                         progress=progress,
                         log=lambda text: print(text, file=sys.stderr, flush=True),
                         stages=args.stages, only=tuple(args.case),
                         blur_calibration=not args.no_blur_calibration,
                         pictures=pictures, config=config)  # fmt: skip
    lines = format_matrix(results)
    for line in lines:
        print(line)
    if args.stages:
        _print_stages([(c.name, m) for c, m in results])
    (out / "matrix.md").write_text("\n".join(lines) + "\n")
    doc = {"format": "lightflow-eval-matrix/1",
           "cases": [dict(case=c.name, rig=c.rig_name, **m.to_dict()) for c, m in results]}
    (out / "matrix.json").write_text(json.dumps(doc, indent=1) + "\n")
    print(f"table written to {out / 'matrix.md'}, metrics to {out / 'matrix.json'}"
          + (f", pictures to {pictures}/" if pictures is not None else ""))
    return 0


def _config(args: argparse.Namespace):
    """The pipeline's configuration the options ask for; None for its default."""
    from lightflow.app.core.pipeline import PipelineConfig

    changed = {}
    if args.stride is not None:
        changed["stride"] = args.stride
    if args.arc_recheck == "on":
        changed["arc_recheck"] = True
    return PipelineConfig(**changed) if changed else None
