"""Batch reprocessing of many recordings on a Dask cluster.

A task is a chunk of frames of one recording.  Replay is pure per frame apart
from the pipeline's slow state (colour-leak estimate and band windows, relearnt
every ``crosstalk_every`` frames; the flow model's blur fit, refitted every
``blur_refit_frames``), so a recording is processed in three steps::

    scan (parallel)   load every frame once: which frames are bad
    state (serial)    run the pipeline on the frames that change its state only,
                      keeping the state found at each chunk start
    chunks (parallel) each chunk seeded with the state before its first frame

Seeded this way every chunk computes exactly what a sequential replay computes
(the batch test checks it), and the serial part is about one frame in 30.  The
LUT is never shipped: every worker loads or builds it once per rig and keeps it
(:func:`worker_pipeline`).  Workers read the frames and write the outputs
themselves (a shared file system on a real cluster); only small metadata and
the pipeline states (a few kB) travel through Dask.

Output, per recording ``OUT/<rec>/``: depth maps ``<frame>.npy`` (formats.md
section 3), point clouds ``ply/<frame>.ply``, and ``.batch/`` bookkeeping (the
plan and one marker per finished chunk) that makes a rerun resume where it
stopped.  ``OUT/batch.json`` holds per recording its status, frame counts, bad
frames and timings.
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from lightflow.app.core.errors import ConfigError, FrameError, LightflowError
from lightflow.app.core.pipeline import DepthPipeline, PipelineConfig
from lightflow.app.core.rig import Rig
from lightflow.app.memory import keep_freed_memory
from lightflow.app.recording import load_frame, read_recording

#: bump when the outputs of a chunk change meaning (invalidates resumable state)
BATCH_FORMAT = "lightflow-batch/2"
#: frames per task
DEFAULT_CHUNK_FRAMES = 60
#: frames per scan task (loading only: cheaper than processing)
SCAN_FRAMES = 120
BOOK_DIR = ".batch"


# ----------------------------------------------------------------------------- pipeline state
#
# The cross-frame state and its schedule belong to DepthPipeline (state(),
# restore(), updates_state_at()); the batch-equals-replay test checks the use here.


def snapshot_state(pipeline: DepthPipeline) -> dict:
    """The cross-frame state of ``pipeline`` now (a picklable dict of copies)."""
    return pipeline.state()


def restore_state(pipeline: DepthPipeline, state: dict, k: int) -> None:
    """Seed a fresh ``pipeline`` with ``state``, its next frame being the ``k``-th good one."""
    pipeline.restore(state, k)


def set_frame_count(pipeline: DepthPipeline, k: int) -> None:
    """Make ``pipeline`` process its next frame as the ``k``-th good frame of a replay."""
    pipeline.restore({"pipeline": {}, "flow": {}}, k)


#: the state pass processes every one of the first frames, while the blur pool fills
EARLY_FRAMES = 9


def updates_state(pipeline: DepthPipeline, k: int) -> bool:
    """Whether the ``k``-th good frame may change the state (else the state pass skips it)."""
    return k < EARLY_FRAMES or pipeline.updates_state_at(k)


# ----------------------------------------------------------------------------- worker side

#: per worker process: LUTs by (rig digest, config) -- built or loaded once, kept
_WORKER_LUTS: dict[tuple[str, str], Any] = {}
_WORKER_LOCK = threading.Lock()


def worker_pipeline(rig: Rig, config: PipelineConfig) -> DepthPipeline:
    """A fresh pipeline (fresh state) sharing this process's LUT for ``rig``.

    The first call per rig loads the LUT from the on-disk cache or builds it;
    later calls reuse it, so tasks never carry the table.
    """
    # one worker thread = one core: numba's and OpenCV's own threads would oversubscribe
    import cv2
    import numba

    numba.set_num_threads(1)
    cv2.setNumThreads(1)
    keep_freed_memory()
    # the LUT depends on the rig, the stride and the depth range only
    key = (rig.digest(), f"{config.stride} {config.depth_range!r}")
    with _WORKER_LOCK:
        lut = _WORKER_LUTS.get(key)
        pipeline = DepthPipeline(rig, config, lut=lut)
        _WORKER_LUTS[key] = pipeline.lut
    return pipeline


def _frame(recording, i: int, image: np.ndarray):
    from lightflow.drivers.base import Frame

    entry = recording.frames[i]
    # as RecordedCamera delivers it (first lap); keep in step with drivers/replay.py
    return Frame(index=i, timestamp=entry.t, exposure_s=recording.exposure_s, image=image,
                 name=entry.stem, bits=recording.bits)  # fmt: skip


def scan_task(rec: str, rig: Rig | None, indices: list[int]) -> list[tuple[int, str]]:
    """Load frames ``indices``: the bad ones as ``(index, one-line reason)``."""
    recording = read_recording(rec, rig)
    bad = []
    for i in indices:
        try:
            load_frame(recording, i)
        except FrameError as exc:
            bad.append((i, str(exc)))
    return bad


def state_task(
    rec: str, rig: Rig | None, config: PipelineConfig, good: list[int], starts: list[int]
) -> dict:
    """The pipeline state a sequential replay has before each of the good-frame
    positions ``starts`` (ascending, >= 0), found by processing only the frames
    that change it (about one in ``crosstalk_every``): ``{"states": [...], "task_s": s}``."""
    t0 = time.perf_counter()
    recording = read_recording(rec, rig)
    pipeline = worker_pipeline(recording.rig, config)
    states: list[dict] = []
    for k, i in enumerate(good):
        while len(states) < len(starts) and starts[len(states)] == k:
            states.append(snapshot_state(pipeline))
        if len(states) == len(starts):
            break
        if updates_state(pipeline, k):
            set_frame_count(pipeline, k)
            # the first frame compared with the next, as in a sequential replay
            ahead = None
            if k == 0 and len(good) > 1:
                ahead = _frame(recording, good[1], load_frame(recording, good[1]))
            pipeline.process(_frame(recording, i, load_frame(recording, i)), ahead)
    return {"states": states, "task_s": time.perf_counter() - t0}


def chunk_task(
    rec: str,
    rig: Rig | None,
    config: PipelineConfig,
    indices: list[int],
    start: int,
    state: dict | None,
    lead: int | None,
    out_dir: str,
    export_depth: bool,
    export_ply: bool,
    marker: str,
    hook: Callable | None = None,
    following: int | None = None,
) -> dict:
    """Process the good frames ``indices`` of a chunk (the first being good frame number
    ``start`` of the recording), write their outputs, then the marker.

    ``state`` is the pipeline state before the good frame ``lead`` (recording index) just
    before the chunk (``None`` for the first chunk): that frame is processed first and not
    written, because a frame's depth also depends on how its lines moved since the one
    before (:func:`lightflow.app.core.flow.moved_lines`).  ``following``: for the first
    chunk, the recording's second good frame, which its first frame is compared with
    (``DepthPipeline.process``), as a sequential replay does.
    """
    if hook is not None:
        hook(rec, indices)
    from lightflow.app.core.results import RunStats
    from lightflow.app.sinks.depth_export import DepthExportSink
    from lightflow.app.sinks.ply import PlyExportSink

    t0 = time.perf_counter()
    recording = read_recording(rec, rig)
    pipeline = worker_pipeline(recording.rig, config)
    if state is not None:
        restore_state(pipeline, state, start - 1)
        pipeline.process(_frame(recording, lead, load_frame(recording, lead)))
    out = Path(out_dir)
    sinks = []
    if export_depth:
        sinks.append(DepthExportSink(out))
    if export_ply:
        sinks.append(PlyExportSink(out / "ply", recording.rig))
    stats = RunStats()
    t_load = t_proc = t_write = 0.0
    bytes_in = 0
    t1 = time.perf_counter()
    for i in indices:
        ta = time.perf_counter()
        image = load_frame(recording, i)
        bytes_in += (recording.root / recording.frames[i].file).stat().st_size
        tb = time.perf_counter()
        ahead = None
        if state is None and i == indices[0] and following is not None:
            ahead = _frame(recording, following, load_frame(recording, following))
        result = pipeline.process(_frame(recording, i, image), ahead)
        tc = time.perf_counter()
        for sink in sinks:
            sink.write(result, stats)
        t_load += tb - ta
        t_proc += tc - tb
        t_write += time.perf_counter() - tc
    for sink in sinks:
        sink.close()
    bytes_out = 0
    for i in indices:
        stem = recording.frames[i].stem
        for p in ((out / f"{stem}.npy") if export_depth else None,
                  (out / f"{stem}_std.npy") if export_depth else None,
                  (out / "ply" / f"{stem}.ply") if export_ply else None):  # fmt: skip
            if p is not None and p.exists():
                bytes_out += p.stat().st_size
    info = {
        "frames": len(indices), "setup_s": t1 - t0, "load_s": t_load, "process_s": t_proc,
        "write_s": t_write, "task_s": time.perf_counter() - t0, "bytes_in": bytes_in,
        "bytes_out": bytes_out, "pid": os.getpid(),
    }  # fmt: skip
    write_json_atomic(Path(marker), info)
    return info


# ----------------------------------------------------------------------------- bookkeeping


def write_json_atomic(path: Path, data: Any) -> None:
    """Write JSON so that readers (and a resumed run) never see half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(data, indent=1) + "\n")
    os.replace(tmp, path)


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None  # absent or damaged bookkeeping: redo that part


def _write_pickle(path: Path, data: Any) -> None:
    """The pipeline states between chunks (our own data, read back only by us)."""
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as fh:
        pickle.dump(data, fh)
    os.replace(tmp, path)


def _read_pickle(path: Path) -> Any:
    try:
        with open(path, "rb") as fh:
            return pickle.load(fh)
    except (OSError, pickle.UnpicklingError, EOFError):
        return None


@dataclass(frozen=True)
class BatchOptions:
    """What every recording of a batch is processed with.

    Attributes
    ----------
    out : Path
        Output folder (``OUT/<rec>/`` per recording, ``OUT/batch.json``).
    rig : Rig, optional
        Overrides each recording's own rig.
    config : PipelineConfig
    export_depth, export_ply : bool
    chunk_frames : int
        Good frames per task.
    hook : callable, optional
        ``hook(rec, indices)`` called on the worker at the start of every chunk
        task (tests use it to kill a worker).
    """

    out: Path
    rig: Rig | None = None
    config: PipelineConfig = field(default_factory=PipelineConfig)
    export_depth: bool = True
    export_ply: bool = False
    chunk_frames: int = DEFAULT_CHUNK_FRAMES
    hook: Callable | None = None

    def chunk_size(self) -> int:
        return max(1, int(self.chunk_frames))


def job_key(rec_json: Path, options: BatchOptions) -> str:
    """Hash of everything a recording's outputs depend on (a change redoes it)."""
    h = hashlib.sha256()
    h.update(BATCH_FORMAT.encode())
    h.update(rec_json.read_bytes())
    h.update((options.rig.digest() if options.rig else "own rig").encode())
    h.update(repr(options.config).encode())
    h.update(f"{options.export_depth} {options.export_ply} {options.chunk_size()}".encode())
    return h.hexdigest()[:16]


@dataclass
class RecordingJob:
    """Client-side progress of one recording."""

    rec: str
    name: str
    out: Path
    n_frames: int = 0
    key: str = ""
    status: str = "pending"  # pending, complete, failed
    error: str = ""
    bad: dict[int, str] = field(default_factory=dict)
    good: list[int] = field(default_factory=list)
    chunks: list[list[int]] = field(default_factory=list)
    chunk_info: dict[int, dict] = field(default_factory=dict)
    scans_left: int = 0
    chunks_left: int = 0
    tasks: int = 0
    skipped: bool = False
    t_start: float = 0.0
    t_end: float = 0.0
    state_s: float = 0.0
    futures: list = field(default_factory=list)

    @property
    def book(self) -> Path:
        return self.out / BOOK_DIR

    def marker(self, c: int) -> Path:
        # the key in the name: a marker of other options never passes for this run's
        return self.book / f"chunk-{self.chunks[c][0]:08d}-{self.key}.json"

    @property
    def frames_done(self) -> int:
        return sum(info["frames"] for info in self.chunk_info.values())

    def entry(self) -> dict:
        infos = list(self.chunk_info.values())
        e: dict[str, Any] = {"recording": self.rec, "status": self.status}
        if self.error:
            e["error"] = self.error
        e.update({
            "frames": self.n_frames, "frames_done": self.frames_done,
            "bad_frames": [self.bad[i] for i in sorted(self.bad)],
            "chunks": len(self.chunks), "tasks_run": self.tasks,
            "skipped_complete": self.skipped, "key": self.key,
        })  # fmt: skip
        if infos:
            e["timings"] = {
                "wall_s": round(self.t_end - self.t_start, 3) if self.t_end else None,
                "state_s": round(self.state_s, 3),
                **{k: round(sum(i[k] for i in infos), 3)
                   for k in ("task_s", "setup_s", "load_s", "process_s", "write_s")},
                "bytes_in": sum(i["bytes_in"] for i in infos),
                "bytes_out": sum(i["bytes_out"] for i in infos),
            }  # fmt: skip
        return e


@dataclass
class BatchReport:
    """What :func:`run_batch` did."""

    jobs: list[RecordingJob]
    wall_s: float
    tasks: int

    @property
    def failed(self) -> list[RecordingJob]:
        return [j for j in self.jobs if j.status != "complete"]

    @property
    def frames_done(self) -> int:
        return sum(j.frames_done for j in self.jobs)

    def fps(self) -> float:
        ran = sum(j.frames_done for j in self.jobs if not j.skipped)
        return ran / self.wall_s if self.wall_s > 0 else 0.0


# ----------------------------------------------------------------------------- client side


def unique_names(recordings: Sequence[str]) -> list[str]:
    """Output folder name per recording: its folder name (must be unique)."""
    names = [Path(r).resolve().name for r in recordings]
    seen: dict[str, str] = {}
    for rec, name in zip(recordings, names, strict=True):
        if name in seen:
            raise ConfigError(
                f"{rec}: same folder name as {seen[name]}: outputs would collide in OUT/{name}/"
            )
        seen[name] = rec
    return names


def local_cluster(n_workers: int, dashboard: bool = True):
    """A LocalCluster of ``n_workers`` single-threaded worker processes, all on 127.0.0.1."""
    import logging

    from distributed import LocalCluster

    # port 0: a free port, so two batches can run side by side
    dash = "127.0.0.1:0" if dashboard else None
    return LocalCluster(
        n_workers=n_workers, threads_per_worker=1, processes=True, host="127.0.0.1",
        scheduler_port=0, dashboard_address=dash, worker_dashboard_address=None,
        silence_logs=logging.ERROR,
    )  # fmt: skip


class BatchProgress:
    """Terminal progress: recordings and frames done (one line, rewritten on a tty)."""

    def __init__(self, jobs: list[RecordingJob], stream: TextIO | None = None):
        self.jobs = jobs
        self.stream = stream if stream is not None else sys.stderr
        self.tty = self.stream.isatty()
        self.t0 = time.perf_counter()
        self.last = 0.0

    def update(self, force: bool = False) -> None:
        now = time.perf_counter()
        if not force and now - self.last < (0.2 if self.tty else 5.0):
            return
        self.last = now
        done = sum(j.status != "pending" for j in self.jobs)
        frames = sum(j.frames_done for j in self.jobs)
        total = sum(len(j.good) if j.good else j.n_frames for j in self.jobs)
        failed = sum(j.status == "failed" for j in self.jobs)
        line = (f"batch: recordings {done}/{len(self.jobs)} done ({failed} failed)  "
                f"frames {frames}/{total}  {now - self.t0:6.1f} s")  # fmt: skip
        if self.tty:
            self.stream.write("\r" + line + "\x1b[K")
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def finish(self) -> None:
        self.update(force=True)
        if self.tty:
            self.stream.write("\n")


def _plan_job(job: RecordingJob, options: BatchOptions) -> None:
    """Read the recording (client side) and pick up what a previous run finished."""
    recording = read_recording(job.rec, options.rig)
    job.n_frames = len(recording.frames)
    if job.n_frames == 0:
        raise FrameError(f"{recording.json_path}: lists no frames")
    job.key = job_key(recording.json_path, options)
    done = _read_json(job.book / "done.json")
    if done and done.get("key") == job.key and done.get("status") == "complete":
        job.status, job.skipped = "complete", True
        job.bad = {int(k): v for k, v in done.get("bad", {}).items()}
        job.good = done.get("good", [])
        job.chunks = done.get("chunks", [])
        job.chunk_info = {c: info for c, info in enumerate(done.get("chunk_info", []))}


def _chunks(job: RecordingJob, size: int) -> None:
    job.chunks = [job.good[k : k + size] for k in range(0, len(job.good), size)]


def run_batch(
    recordings: Sequence[str],
    options: BatchOptions,
    scheduler: str | None = None,
    n_workers: int | None = None,
    stream: TextIO | None = None,
    client=None,
) -> BatchReport:
    """Process ``recordings`` on Dask; write outputs and ``OUT/batch.json``.

    Parameters
    ----------
    recordings : sequence of str
        Recording folders (names must be unique).
    options : BatchOptions
    scheduler : str, optional
        Address of a running Dask scheduler; without it a :func:`local_cluster` is started.
    n_workers : int, optional
        Workers of the local cluster (default: the core count).
    stream : file, optional
        Progress output (default stderr).
    client : distributed.Client, optional
        Use this client (tests, benchmarks) instead of connecting or starting one.

    Returns
    -------
    BatchReport
        A recording that cannot be read or processed is ``failed`` with one line;
        the others still finish.
    """
    out = Path(options.out)
    out.mkdir(parents=True, exist_ok=True)
    names = unique_names(recordings)
    jobs = [RecordingJob(str(r), n, out / n) for r, n in zip(recordings, names, strict=True)]
    for job in jobs:
        try:
            _plan_job(job, options)
        except LightflowError as exc:
            job.status, job.error = "failed", str(exc)
    progress = BatchProgress(jobs, stream)
    t0 = time.perf_counter()
    pending = [j for j in jobs if j.status == "pending"]
    tasks = 0
    if pending:
        if client is not None:
            tasks = _run_jobs(client, pending, options, progress, jobs)
        elif scheduler:
            from distributed import Client

            with Client(scheduler) as c:
                tasks = _run_jobs(c, pending, options, progress, jobs)
        else:
            from distributed import Client

            n = n_workers or os.cpu_count() or 1
            prebuild_luts(pending, options)
            with local_cluster(n) as cluster, Client(cluster) as c:
                print(f"batch: local Dask cluster, {n} workers, dashboard {cluster.dashboard_link}",
                      file=progress.stream, flush=True)  # fmt: skip
                tasks = _run_jobs(c, pending, options, progress, jobs)
    progress.finish()
    report = BatchReport(jobs, time.perf_counter() - t0, tasks)
    write_batch_json(out, report)
    return report


def prebuild_luts(jobs: Sequence[RecordingJob], options: BatchOptions) -> None:
    """Build each rig's LUT once here, on every core, into the on-disk cache that local
    workers then load (instead of each worker building it on one core)."""
    from lightflow.app.core.depth_model import load_or_build_lut
    from lightflow.app.status import Progress

    rigs = {}
    for job in jobs:
        try:
            rig = options.rig or read_recording(job.rec).rig
        except LightflowError:
            continue  # reported by its tasks
        rigs[rig.digest()] = rig
    cfg = options.config
    for rig in rigs.values():
        load_or_build_lut(rig, cfg.stride, cfg.depth_range, Progress("building depth LUT"))


def write_batch_json(out: Path, report: BatchReport) -> None:
    write_json_atomic(out / "batch.json", {
        "format": BATCH_FORMAT,
        "recordings": {j.name: j.entry() for j in report.jobs},
    })  # fmt: skip


def _run_jobs(client, pending, options: BatchOptions, progress: BatchProgress, jobs) -> int:
    """The event loop: submit scans, then the state pass, then chunks, per recording."""
    from distributed import as_completed

    size = options.chunk_size()
    rig = options.rig
    cfg = options.config
    kind: dict[Any, tuple[RecordingJob, str, int]] = {}
    ac = as_completed()
    submitted = 0

    def submit(job, what, c, fn, *args):
        nonlocal submitted
        fut = client.submit(fn, *args, pure=False, key=f"{what}-{job.name}-{c}-{job.key}")
        kind[fut] = (job, what, c)
        job.futures.append(fut)
        ac.add(fut)
        job.tasks += 1
        submitted += 1

    def submit_chunks(job, states: list[dict]) -> None:
        """Chunk c > 0 starts at good frame c * size, seeded with states[c - 1] (the state
        before the good frame ahead of it, which it processes first)."""
        job.chunks_left = 0
        for c, indices in enumerate(job.chunks):
            info = _read_json(job.marker(c))
            if info is not None and info.get("frames") == len(indices):
                job.chunk_info[c] = info  # finished by an earlier run
                continue
            state = None if c == 0 else states[c - 1]
            lead = None if c == 0 else job.good[c * size - 1]
            submit(job, "chunk", c, chunk_task, job.rec, rig, cfg, indices, c * size, state,
                   lead, str(job.out), options.export_depth, options.export_ply,
                   str(job.marker(c)), options.hook,
                   job.good[1] if c == 0 and len(job.good) > 1 else None)  # fmt: skip
            job.chunks_left += 1
        if job.chunks_left == 0:
            finish(job)

    def after_scan(job) -> None:
        job.good = [i for i in range(job.n_frames) if i not in job.bad]
        if not job.good:
            first = job.bad[min(job.bad)]
            fail(job, f"{job.rec}: none of the {job.n_frames} frames could be replayed ({first})")
            return
        _chunks(job, size)
        write_json_atomic(job.book / "plan.json", {
            "key": job.key, "bad": {str(i): v for i, v in job.bad.items()}, "good": job.good,
        })  # fmt: skip
        # each chunk c > 0 starts from the frame ahead of it (see chunk_task)
        starts = [c * size - 1 for c in range(1, len(job.chunks))]
        cached = _read_pickle(job.book / "states.pkl")
        if cached and cached.get("key") == job.key and len(cached["states"]) == len(starts):
            submit_chunks(job, cached["states"])
        elif starts:
            submit(job, "state", 0, state_task, job.rec, rig, cfg, job.good, starts)
        else:
            submit_chunks(job, [])

    def finish(job) -> None:
        job.status = "complete"
        job.t_end = time.perf_counter()
        write_json_atomic(job.book / "done.json", {
            "key": job.key, "status": "complete",
            "bad": {str(i): v for i, v in job.bad.items()}, "good": job.good,
            "chunks": job.chunks, "chunk_info": [job.chunk_info[c] for c in range(len(job.chunks))],
        })  # fmt: skip
        write_batch_json(Path(options.out), BatchReport(jobs, 0.0, submitted))

    def fail(job, line: str) -> None:
        job.status, job.error = "failed", line
        job.t_end = time.perf_counter()
        for f in job.futures:
            if not f.done():
                f.cancel()
        write_batch_json(Path(options.out), BatchReport(jobs, 0.0, submitted))

    for job in pending:
        job.t_start = time.perf_counter()
        plan = _read_json(job.book / "plan.json")
        if plan and plan.get("key") == job.key:
            job.bad = {int(k): v for k, v in plan["bad"].items()}
            after_scan(job)
            continue
        for c, k in enumerate(range(0, job.n_frames, SCAN_FRAMES)):
            idx = list(range(k, min(k + SCAN_FRAMES, job.n_frames)))
            submit(job, "scan", c, scan_task, job.rec, rig, idx)
            job.scans_left += 1
    progress.update(force=True)

    for fut in ac:
        job, what, c = kind.pop(fut)
        if job.status != "pending":
            continue  # a recording that already failed: its cancelled leftovers
        if fut.status != "finished":
            fail(job, _error_line(job, fut))
            progress.update(force=True)
            continue
        result = fut.result()
        if what == "scan":
            job.bad.update({i: line for i, line in result})
            job.scans_left -= 1
            if job.scans_left == 0:
                after_scan(job)
        elif what == "state":
            job.state_s = result["task_s"]  # the serial part of a recording
            _write_pickle(job.book / "states.pkl", {"key": job.key, "states": result["states"]})
            submit_chunks(job, result["states"])
        else:
            job.chunk_info[c] = result
            job.chunks_left -= 1
            if job.chunks_left == 0:
                finish(job)
        progress.update(force=job.status != "pending")
    return submitted


def _error_line(job: RecordingJob, fut) -> str:
    """One line for a task that failed for good (after Dask's retries)."""
    if fut.status == "cancelled":
        return f"{job.rec}: cancelled"
    exc = fut.exception()
    if isinstance(exc, LightflowError):
        return str(exc)
    name = type(exc).__name__
    if name == "KilledWorker":
        return f"{job.rec}: workers kept dying on this task ({exc})"
    return f"{job.rec}: {name}: {exc}"


# ----------------------------------------------------------------------------- summary


def summary_table(report: BatchReport) -> list[str]:
    """One line per recording: status, frames done/total, bad frames, time."""
    rows = [("recording", "status", "frames", "bad", "tasks", "task s", "note")]
    for j in report.jobs:
        e = j.entry()
        t = e.get("timings", {})
        status = "skipped" if j.skipped else j.status
        rows.append((j.name, status, f"{j.frames_done}/{j.n_frames}",
                     str(len(j.bad)), str(j.tasks if not j.skipped else 0),
                     f"{t.get('task_s', 0):.1f}", j.error))  # fmt: skip
    widths = [max(len(r[k]) for r in rows) for k in range(6)]
    lines = []
    for r in rows:
        note = "  " + r[6] if r[6] else ""
        lines.append("  ".join(r[k].ljust(widths[k]) for k in range(6)) + note)
    lines.append(
        f"{sum(j.status == 'complete' for j in report.jobs)} of {len(report.jobs)} recordings "
        f"complete, {report.frames_done} frames, {report.tasks} tasks run in {report.wall_s:.1f} s"
    )
    return lines
