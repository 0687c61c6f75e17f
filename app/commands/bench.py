"""``lightflow bench``: time per frame of each depth-pipeline stage at the rig's native size."""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from lightflow.app.core.errors import ConfigError, LightflowError
from lightflow.app.options import STRIDES

DESCRIPTION = """\
Measure how long the depth pipeline takes per frame, stage by stage, at the
rig's native camera size (1600x1200 for the example rigs).  Frames are
rendered with the synthetic camera first and kept in memory, so file decoding
is not counted; the depth table (LUT) is built or loaded before timing, and a
warm-up pass compiles the numba kernels.  Reported: median and 90th percentile
per stage, the wall time per frame, the frame rate, and the CPU time per frame
of all the pipeline's threads (it varies far less than the wall time when other
work shares the cores).

End to end: the rendered frames are written as a recording (PNG, like
`capture --record`), then replayed into the same (warm) pipeline with a
depth export (.npy), as `lightflow replay REC --export-depth OUT` does:
decoding runs ahead on a reader thread and the export writes on its own
thread, so the stages overlap.  Reported: frames per second and wall time per
frame of the whole replay, and the median time per stage (decode, pipeline,
write) measured inside that run.  --e2e-frames 0 skips it.

Against the paper's plain reference (lightflow.app.reference: NumPy, row by
row, the benchmark's baseline, not used by the pipeline): recordings of
--compare-frames and of 2 frames are replayed with `lightflow replay REC
--export-depth OUT` (a fresh process each) and with the reference (decode,
depth, write, one after the other), each run --compare-repeats times; the
difference of the fastest runs divided by the difference in frames is the
marginal time per frame, so that start-up cancels.  Reported: both marginal
times and the speed-up.  --compare-frames 0 skips it.

With --recorder, also measures the sustained write rate of the recorder
(1600x1200 RGB PNG at 30 fps for 5 s): frames/s, MiB/s and dropped frames."""

EPILOG = """\
examples:
  lightflow bench                       # two-projector rig, board scene, 1600x1200
  lightflow bench --rig single-projector --frames 50
  lightflow bench --recorder            # also the recorder: 1600x1200 PNG at 30 fps
  lightflow bench --e2e-frames 40       # a longer end-to-end replay with export
  lightflow bench --compare-frames 0    # without the comparison with the reference"""

#: frames in the end-to-end replay by default
E2E_FRAMES = 16
#: the long recording of the side-by-side comparison (the short one has 2 frames)
COMPARE_FRAMES = 12
COMPARE_SHORT = 2


WARMUP = 2


def register(subparsers) -> None:
    from lightflow.drivers.sim.scenes import SCENES

    p = subparsers.add_parser(
        "bench",
        help="time the depth pipeline per stage (and optionally the recorder)",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--rig",
        default="two-projector",
        metavar="RIG",
        help="rig file or example rig name (default: two-projector)",
    )
    p.add_argument(
        "--scene",
        default="board",
        choices=list(SCENES),
        metavar="NAME",
        help=f"scene to render ({', '.join(SCENES)}; default: board)",
    )
    p.add_argument(
        "--frames", type=int, default=20, metavar="N", help="timed process() calls (default: 20)"
    )
    p.add_argument(
        "--stride",
        type=int,
        default=None,
        choices=STRIDES,
        help="analysis grid stride (default: the pipeline's; 8 takes about half the CPU)",
    )
    p.add_argument(
        "--e2e-frames",
        type=int,
        default=E2E_FRAMES,
        metavar="N",
        help=f"frames in the end-to-end replay with export (default: {E2E_FRAMES}; 0: skip it)",
    )
    p.add_argument(
        "--compare-frames",
        type=int,
        default=COMPARE_FRAMES,
        metavar="N",
        help=f"frames of the long recording replayed side by side with the plain reference "
        f"(default: {COMPARE_FRAMES}; 0: skip the comparison)",
    )
    p.add_argument(
        "--compare-repeats",
        type=int,
        default=3,
        metavar="N",
        help="runs of each replay in the comparison; the fastest counts (default: 3)",
    )
    p.add_argument("--recorder", action="store_true", help="also benchmark the recording writer")
    p.set_defaults(func=run)


def _progress(stage: str, i: int, n: int) -> None:
    end = "\n" if i == n else ""
    print(f"\r{stage}: {i}/{n}", end=end, file=sys.stderr, flush=True)


def stage_table(timings: list[dict[str, float]], wall_ms: list[float]) -> list[str]:
    """Median and p90 per stage (in pipeline order) plus wall time, as text lines."""
    stages = [k for k in timings[0] if k != "total"]
    rows = []
    for name in [*stages, "total"]:
        v = np.array([t.get(name, np.nan) for t in timings])
        rows.append((name, np.nanmedian(v), np.nanpercentile(v, 90)))
    rows.append(("wall per frame", float(np.median(wall_ms)), float(np.percentile(wall_ms, 90))))
    width = max(len(r[0]) for r in rows)
    out = [f"{'stage':<{width}}  {'median ms':>9}  {'p90 ms':>8}",
           f"{'-' * width}  {'-' * 9}  {'-' * 8}"]  # fmt: skip
    for name, med, p90 in rows:
        if name == "total":
            out.append(out[1])
        out.append(f"{name:<{width}}  {med:>9.1f}  {p90:>8.1f}")
    return out


def run(args: argparse.Namespace) -> int:
    from lightflow.app.core.pipeline import DepthPipeline, PipelineConfig
    from lightflow.app.core.rig import resolve_rig
    from lightflow.drivers.sim.synthetic import SyntheticCamera

    if args.frames < 1:
        raise ConfigError(f"--frames: expected at least 1, got {args.frames}")
    rig = resolve_rig(args.rig)
    cam = rig.camera
    config = PipelineConfig() if args.stride is None else PipelineConfig(stride=args.stride)
    print(
        f"rig {args.rig}: camera {cam.width}x{cam.height}, {len(rig.projectors)} projector(s),"
        f" scene {args.scene}, stride {config.stride}; {_load()}"
    )
    n_render = 2
    camera = SyntheticCamera(rig, args.scene, frames=n_render)
    frames = []
    with camera:
        _progress("rendering test frames", 0, n_render)
        for i, frame in enumerate(camera.frames()):
            frames.append(frame)
            _progress("rendering test frames", i + 1, n_render)
    t0 = time.perf_counter()
    pipeline = DepthPipeline(rig, config, progress=lambda i, n: _progress("depth table", i, n))
    print(f"depth table ready in {time.perf_counter() - t0:.1f} s (not timed)", file=sys.stderr)
    for i in range(WARMUP):  # the first calls compile the numba kernels
        pipeline.process(frames[i % len(frames)])
        _progress("warm-up", i + 1, WARMUP)
    timings, wall = [], []
    cpu0 = time.process_time()
    for i in range(args.frames):
        frame = frames[i % len(frames)]
        t = time.perf_counter()
        result = pipeline.process(frame)
        wall.append((time.perf_counter() - t) * 1e3)
        timings.append(dict(result.timings_ms))
        _progress("timing", i + 1, args.frames)
    cpu_ms = (time.process_time() - cpu0) / args.frames * 1e3
    print()
    for line in stage_table(timings, wall):
        print(line)
    med = float(np.median(wall))
    print(
        f"\n{1e3 / med:.1f} frames/s (median wall time {med:.1f} ms over {args.frames} frames,"
        f" {sum(wall) / 1e3:.2f} s in all)"
    )
    # CPU time counts every thread of this process and not the waits for a core that other
    # work holds: on a shared machine it varies far less than the wall time
    print(f"CPU per frame: {cpu_ms:.1f} ms (all threads of the pipeline)")
    if args.e2e_frames < 0:
        raise ConfigError(f"--e2e-frames: expected 0 or more, got {args.e2e_frames}")
    if args.e2e_frames:
        for line in end_to_end(rig, pipeline, frames, args.e2e_frames):
            print(line)
    if args.compare_frames:
        if args.compare_frames <= COMPARE_SHORT or args.compare_repeats < 1:
            raise ConfigError(
                f"--compare-frames: expected 0 or more than {COMPARE_SHORT}, got "
                f"{args.compare_frames} (--compare-repeats: at least 1)"
            )
        if rig.single_projector:
            print("\nreference comparison: skipped (the reference needs a two-projector rig)")
        else:
            for line in versus_reference(rig, pipeline, frames, args.compare_frames,
                                         args.compare_repeats, config.stride):  # fmt: skip
                print(line)
    if args.recorder:
        _run_recorder()
    print(f"\nat the end: {_load()}")
    return 0


def _load() -> str:
    """The machine's load average: other work on the cores changes every figure."""
    one, five, _ = os.getloadavg()
    return f"load average {one:.1f} (1 min), {five:.1f} (5 min) on {os.cpu_count()} cores"


class _TimedExport:
    """A depth export that records how long each write took (on its writer thread)."""

    def __init__(self, sink):
        self.sink = sink
        self.write_ms: list[float] = []

    def write(self, result, stats) -> None:
        t = time.perf_counter()
        self.sink.write(result, stats)
        self.write_ms.append((time.perf_counter() - t) * 1e3)

    def close(self) -> None:
        self.sink.close()


def end_to_end(rig, pipeline, frames, n: int) -> list[str]:
    """Replay an ``n``-frame recording of ``frames`` with a depth export; the report lines.

    The pipeline must be warm (depth table loaded, kernels compiled): start-up
    is not what this measures.
    """
    import dataclasses
    import tempfile
    from pathlib import Path

    from lightflow.app.recording import RecordingWriter, load_frame
    from lightflow.app.replay_camera import RecordedCamera
    from lightflow.app.runner import Runner
    from lightflow.app.sinks.depth_export import DepthExportSink

    cam = rig.camera
    with tempfile.TemporaryDirectory(prefix="lightflow-bench-") as tmp:
        rec, out = Path(tmp) / "rec", Path(tmp) / "depth"
        period = 1.0 / 30
        with RecordingWriter(rec, rig, frames[0].exposure_s, put_timeout_s=None) as writer:
            for i in range(n):
                f = frames[i % len(frames)]
                writer.write(dataclasses.replace(f, index=i, timestamp=i * period, name=""))
                _progress("writing the recording", i + 1, n)
        camera = RecordedCamera(rec, rig=rig)
        decode_ms = []
        for i in range(min(n, 8)):  # the decode cost alone, as the reader thread pays it
            t = time.perf_counter()
            load_frame(camera.recording, i)
            decode_ms.append((time.perf_counter() - t) * 1e3)
        export = _TimedExport(DepthExportSink(out))
        pipeline_ms: list[float] = []
        runner = Runner(
            camera,
            pipeline,
            [export],
            lossless=True,
            count_gaps=False,
            on_result=lambda r: pipeline_ms.append(r.timings_ms.get("total", 0.0)),
        )
        t = time.perf_counter()
        with camera:
            stats = runner.run()
        wall = time.perf_counter() - t
        # depth maps, not their <frame>_std.npy companions
        exported = len([f for f in out.glob("*.npy") if not f.stem.endswith("_std")])
    per_frame = wall / n * 1e3
    sequential = float(np.median(decode_ms) + np.median(pipeline_ms) + np.median(export.write_ms))
    return [
        "",
        f"end to end: replay of a {n}-frame {cam.width}x{cam.height} recording with "
        f"--export-depth (decode, pipeline and write overlapped)",
        f"  {n / wall:.1f} frames/s, {per_frame:.1f} ms per frame wall "
        f"({wall:.2f} s in all, threads' start-up included)",
        f"  per stage, median ms: decode {np.median(decode_ms):.1f}, pipeline "
        f"{np.median(pipeline_ms):.1f}, write {np.median(export.write_ms):.1f} "
        f"(one after the other: {sequential:.1f})",
        f"  frames processed {stats.frames_done} of {n}, exported {exported}, "
        f"dropped {stats.dropped}",
    ]


def _write_recording(path, rig, frames, n: int) -> None:
    """An ``n``-frame recording cycling through ``frames`` (PNG, as ``capture --record``)."""
    import dataclasses

    from lightflow.app.recording import RecordingWriter

    period = 1.0 / 30
    with RecordingWriter(path, rig, frames[0].exposure_s, put_timeout_s=None) as writer:
        for i in range(n):
            f = frames[i % len(frames)]
            writer.write(dataclasses.replace(f, index=i, timestamp=i * period, name=""))


def versus_reference(rig, pipeline, frames, n: int, repeats: int, stride: int):
    """Marginal time per frame of ``replay --export-depth`` and of the plain reference.

    Both replay an ``n``-frame and a 2-frame recording of ``frames``;
    ``lightflow replay`` runs as its own process (as a user runs it: start-up,
    read-ahead, pipeline, background export), the reference in this process
    (:func:`lightflow.app.reference.reference_replay`: decode, depth, write).
    The fastest of ``repeats`` runs of each counts.  Returns the report lines.
    """
    import subprocess
    import tempfile
    from pathlib import Path

    from lightflow.app.reference import reference_replay

    cam = rig.camera
    lengths = (COMPARE_SHORT, n)
    best = {(tool, k): float("inf") for tool in ("replay", "reference") for k in lengths}
    with tempfile.TemporaryDirectory(prefix="lightflow-bench-") as tmp:
        recs = {k: Path(tmp) / f"rec{k}" for k in lengths}
        for k in lengths:
            _write_recording(recs[k], rig, frames, k)
        total = 2 * repeats * len(lengths)
        done = 0
        for r in range(repeats):
            for k in lengths:  # interleaved: a load spike hits both lengths alike
                out = Path(tmp) / f"out-{k}-{r}"
                cmd = [sys.executable, "-m", "lightflow.app.cli", "replay", str(recs[k]),
                       "--export-depth", str(out / "replay")]  # fmt: skip
                if stride != 4:
                    cmd += ["--stride", str(stride)]
                t = time.perf_counter()
                proc = subprocess.run(cmd, capture_output=True, text=True)
                wall = time.perf_counter() - t
                if proc.returncode != 0:
                    last = (proc.stderr.strip().splitlines() or ["no message"])[-1]
                    raise LightflowError(f"bench: lightflow replay {recs[k]} failed: {last}")
                best["replay", k] = min(best["replay", k], wall)
                done += 1
                _progress("replay vs reference", done, total)
                t = time.perf_counter()
                reference_replay(recs[k], out / "reference", lut=pipeline.lut)
                best["reference", k] = min(best["reference", k], time.perf_counter() - t)
                done += 1
                _progress("replay vs reference", done, total)
    extra = n - COMPARE_SHORT
    ms = {tool: (best[tool, n] - best[tool, COMPARE_SHORT]) / extra * 1e3
          for tool in ("replay", "reference")}  # fmt: skip
    return [
        "",
        f"versus the paper's plain reference (lightflow.app.reference), {cam.width}x{cam.height}, "
        f"marginal time per frame ({n}- vs {COMPARE_SHORT}-frame recording, fastest of "
        f"{repeats} runs):",
        f"  lightflow replay --export-depth  {ms['replay']:7.1f} ms per frame "
        f"(runs of {best['replay', COMPARE_SHORT]:.2f} s and {best['replay', n]:.2f} s)",
        f"  reference (decode, depth, write) {ms['reference']:7.1f} ms per frame "
        f"(runs of {best['reference', COMPARE_SHORT]:.2f} s and {best['reference', n]:.2f} s)",
        f"  speed-up {ms['reference'] / ms['replay']:.1f}x",
    ]


def _run_recorder() -> None:
    from lightflow.app.recording import benchmark_recorder

    seconds = 5.0
    print(f"\nrecorder: 1600x1200 RGB PNG offered at 30 fps for {seconds:g} s ...", flush=True)
    r = benchmark_recorder(1600, 1200, 30.0, seconds)
    print(f"  written  {r['written']:.0f} of {r['offered']:.0f} frames, dropped {r['dropped']:.0f}")
    print(
        f"  rate     {r['fps']:.1f} frames/s, {r['mib_per_s']:.1f} MiB/s "
        f"({r['mib_per_frame']:.2f} MiB per frame)"
    )
