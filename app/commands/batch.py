"""``lightflow batch``: reprocess many recordings on a Dask cluster (local by default)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from lightflow.app.core.errors import ConfigError
from lightflow.app.options import add_pipeline_options, pipeline_config

HELP = "reprocess many recordings on Dask (a local cluster, or one by address)"

DESCRIPTION = """\
Run the depth pipeline over every frame of each recording REC, split into
chunks of frames that run as Dask tasks.  Without --scheduler a local cluster
of --workers processes is started, listening on 127.0.0.1 only.  Outputs go to
OUT/<rec>/ (depth maps <frame>.npy, point clouds ply/<frame>.ply), with
OUT/batch.json holding per recording its status, frame counts, bad frames and
timings.  Results equal a sequential `lightflow replay`.  Running the same
command again skips what is complete and resumes what is not.  Exit status 2
when a recording failed or had bad frames (each named in batch.json).

Needs the batch extra: pip install 'lightflow[batch]'."""

EPILOG = """\
examples:
  lightflow batch rec-a rec-b rec-c --out out/batch
  lightflow batch recs/* --out out/batch --export-ply --workers 2
  lightflow batch recs/* --out /shared/out --scheduler tcp://10.0.0.5:8786
  lightflow batch rec-a --out /tmp/bench --bench        # frames/s with 1 and 2 workers"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "batch", help=HELP, description=DESCRIPTION, epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    p.add_argument("recordings", nargs="+", metavar="REC", help="recording folders")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--rig", metavar="RIG", help="rig file overriding each recording's own rig")
    p.add_argument("--export-depth", action="store_true",
                   help="write OUT/<rec>/<frame>.npy depth maps (the default output)")
    p.add_argument("--export-ply", action="store_true",
                   help="write OUT/<rec>/ply/<frame>.ply point clouds")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="submit to a running Dask scheduler, e.g. tcp://host:8786 "
                        "(workers must see REC and OUT at the same paths)")
    p.add_argument("--workers", type=int, metavar="N",
                   help="workers of the local cluster (default: the core count)")
    p.add_argument("--chunk-frames", type=int, default=None, metavar="N",
                   help="frames per task (default 60)")
    p.add_argument("--bench", action="store_true",
                   help="measure frames/s with 1 and 2 local workers on copies of REC in OUT, "
                        "and estimate a 32-worker cluster")
    add_pipeline_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    try:
        import distributed  # noqa: F401
    except ImportError:
        raise ConfigError(
            "batch needs Dask: pip install 'lightflow[batch]' (dask and distributed)"
        ) from None
    from lightflow.app import batch
    from lightflow.app.core.rig import resolve_rig

    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers: expected at least 1, got {args.workers}")
    if args.scheduler and args.workers is not None:
        raise ConfigError("--workers: only for the local cluster, not with --scheduler")
    chunk = args.chunk_frames if args.chunk_frames is not None else batch.DEFAULT_CHUNK_FRAMES
    if chunk < 1:
        raise ConfigError(f"--chunk-frames: expected at least 1, got {chunk}")
    options = batch.BatchOptions(
        out=Path(args.out),
        rig=resolve_rig(args.rig) if args.rig else None,
        config=pipeline_config(args),
        export_depth=args.export_depth or not args.export_ply,
        export_ply=args.export_ply,
        chunk_frames=chunk,
    )  # fmt: skip
    if args.bench:
        from lightflow.app import batch_bench

        for line in batch_bench.bench(args.recordings, options):
            print(line, flush=True)
        return 0
    report = batch.run_batch(args.recordings, options, scheduler=args.scheduler,
                             n_workers=args.workers)  # fmt: skip
    for line in batch.summary_table(report):
        print(line)
    print(f"per recording status, bad frames and timings: {Path(args.out) / 'batch.json'}")
    failed = report.failed
    with_bad = [j for j in report.jobs if j.status == "complete" and j.bad]
    for j in failed:
        print(f"lightflow: error: {j.error}", file=sys.stderr)
    if failed or with_bad:
        if with_bad:
            n = sum(len(j.bad) for j in with_bad)
            print(f"lightflow: error: {n} bad frames in {len(with_bad)} recordings "
                  f"(listed in batch.json)", file=sys.stderr)  # fmt: skip
        return 2
    return 0
