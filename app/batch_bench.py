"""Throughput of ``lightflow batch`` against the number of workers, and a cluster estimate.

:func:`bench` runs the same batch with 1 and 2 local workers (single-threaded
worker processes; LUT and compiled kernels warmed on every worker first, so
the numbers are the steady state a long batch sees), then extrapolates a
32-worker cluster from the per-task timings and the bytes each task moves.
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Iterator, Sequence
from dataclasses import replace
from pathlib import Path

from lightflow.app.batch import BatchOptions, BatchReport, run_batch, worker_pipeline
from lightflow.app.core.depth_model import load_or_build_lut
from lightflow.app.recording import load_frame, read_recording
from lightflow.drivers.base import Frame

#: assumed for the 32-worker estimate: shared storage / network bandwidth (10 GbE)
CLUSTER_NET_BYTES_S = 1.25e9
#: scheduler overhead per task (Dask's documented order of magnitude: about 1 ms)
SCHEDULER_S_PER_TASK = 1e-3


def replicate_recording(src: str | Path, dst: str | Path, n_frames: int) -> Path:
    """A recording of ``n_frames`` frames made by cycling ``src``'s frames (new names, new times).

    Processing cost does not depend on which frame comes when, so this makes
    long benchmark recordings without rendering them.
    """
    src, dst = Path(src), Path(dst)
    data = json.loads((src / "recording.json").read_text())
    frames = data["frames"]
    period = (frames[-1]["t"] - frames[0]["t"]) / max(1, len(frames) - 1) or 1 / 60
    (dst / "frames").mkdir(parents=True, exist_ok=True)
    out = []
    for i in range(n_frames):
        f = frames[i % len(frames)]
        name = f"frames/{i:06d}{Path(f['file']).suffix}"
        target = dst / name
        if not target.exists():
            try:
                target.hardlink_to(src / f["file"])
            except OSError:
                shutil.copyfile(src / f["file"], target)
        out.append({"file": name, "t": frames[0]["t"] + i * period})
    data["frames"] = out
    (dst / "recording.json").write_text(json.dumps(data, indent=1))
    return dst


def _warm(rec: str, rig, config) -> int:
    """Load the LUT and the compiled kernels (numba's cache) on a worker: one frame."""
    recording = read_recording(rec, rig)
    pipeline = worker_pipeline(recording.rig, config)
    image = load_frame(recording, 0)
    pipeline.process(Frame(index=0, timestamp=0.0, exposure_s=recording.exposure_s, image=image,
                           bits=recording.bits))  # fmt: skip
    return 0


def _run(recs: Sequence[str], options: BatchOptions, n_workers: int) -> BatchReport:
    from distributed import Client

    from lightflow.app.batch import local_cluster

    rigs = {}
    for r in recs:
        rigs.setdefault(read_recording(r, options.rig).rig.digest(), r)
    for r in rigs.values():  # into the disk cache, on every core
        rig = read_recording(r, options.rig).rig
        load_or_build_lut(rig, options.config.stride, options.config.depth_range)
    with local_cluster(n_workers, dashboard=False) as cluster, Client(cluster) as client:
        for r in rigs.values():
            client.run(_warm, r, options.rig, options.config)
        t0 = time.perf_counter()
        report = run_batch(recs, options, client=client, stream=_Null())
        report.wall_s = time.perf_counter() - t0
    return report


class _Null:
    def write(self, s: str) -> None:
        pass

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return False


def bench(
    recordings: Sequence[str], options: BatchOptions, frames_per_recording: int = 60,
    n_recordings: int = 4, workers: Sequence[int] = (1, 2),
) -> Iterator[str]:
    """Yield report lines: frames/s per worker count, speed-up, 32-worker estimate.

    ``n_recordings`` recordings of ``frames_per_recording`` frames are made by
    cycling through ``recordings`` and their frames (under ``options.out/bench-src``);
    every run writes to a fresh ``options.out/bench-<n>``, whose depth maps are
    deleted afterwards (its ``batch.json`` is kept).
    """
    root = Path(options.out)
    srcs = []
    for k in range(max(n_recordings, len(recordings))):
        rec = recordings[k % len(recordings)]
        dst = root / "bench-src" / f"{k:02d}-{Path(rec).resolve().name}"
        srcs.append(str(replicate_recording(rec, dst, frames_per_recording)))
    yield (f"bench: {len(srcs)} recordings x {frames_per_recording} frames, "
           f"chunks of {options.chunk_size()} frames, stride {options.config.stride}")  # fmt: skip
    fps = {}
    last = None
    for n in workers:
        out = root / f"bench-{n}"
        shutil.rmtree(out, ignore_errors=True)
        report = _run(srcs, replace(options, out=out), n)
        if report.failed:
            yield f"bench: {report.failed[0].error}"
            return
        fps[n] = report.fps()
        last = report
        busy = sum(sum(i["task_s"] for i in j.chunk_info.values()) + j.state_s
                   for j in report.jobs)  # fmt: skip
        per_frame = sum(i["task_s"] for j in report.jobs for i in j.chunk_info.values())
        yield (f"workers {n}: {report.frames_done} frames in {report.wall_s:.2f} s = "
               f"{fps[n]:.2f} frames/s ({report.tasks} tasks; workers busy with chunks and "
               f"state passes {100 * busy / (n * report.wall_s):.0f} % of the time, "
               f"chunk tasks {1e3 * per_frame / report.frames_done:.0f} ms/frame)")  # fmt: skip
        for job in report.jobs:  # the depth maps: gigabytes at full resolution
            shutil.rmtree(job.out, ignore_errors=True)
    if len(fps) >= 2:
        a, b = sorted(fps)[:2]
        yield f"speed-up {b} vs {a} workers: {fps[b] / fps[a]:.2f}x"
    # the cluster estimate from the last run's per-task records
    infos = [i for j in last.jobs for i in j.chunk_info.values()]
    frames = sum(i["frames"] for i in infos)
    per_frame_s = sum(i["task_s"] for i in infos) / frames
    bytes_per_frame = sum(i["bytes_in"] + i["bytes_out"] for i in infos) / frames
    frames_per_task = frames / len(infos)
    state_per_frame = sum(max(0.0, j.state_s) for j in last.jobs) / frames
    n = 32
    compute = n / (per_frame_s + SCHEDULER_S_PER_TASK / frames_per_task)
    io = CLUSTER_NET_BYTES_S / bytes_per_frame
    alone = 1.0 / (state_per_frame + per_frame_s / n)
    yield (f"per task: {frames_per_task:.0f} frames, {per_frame_s * 1e3:.1f} ms/frame on one "
           f"worker (load {sum(i['load_s'] for i in infos) / frames * 1e3:.1f}, process "
           f"{sum(i['process_s'] for i in infos) / frames * 1e3:.1f}, write "
           f"{sum(i['write_s'] for i in infos) / frames * 1e3:.1f}), "
           f"{bytes_per_frame / 1e6:.2f} MB/frame read+written; serial state pass "
           f"{state_per_frame * 1e3:.2f} ms/frame per recording")  # fmt: skip
    yield (f"32-worker estimate: {min(compute, io):.0f} frames/s with many recordings in flight "
           f"(compute bound {compute:.0f}, storage bound {io:.0f} at "
           f"{CLUSTER_NET_BYTES_S / 1e9:.2f} GB/s shared storage); one recording alone "
           f"{alone:.0f} frames/s (its state pass is serial)")  # fmt: skip
