"""Cold starts of ``lightflow demo``: what a first run on a new machine costs.

Each run gets an empty ``XDG_CACHE_HOME`` (no depth or profile tables, no numba
kernels) and no numba cache files beside the sources, as a fresh clone has.
Prints, per run, the load average before and after (the machine may be shared),
the first depth picture and the whole demo in wall and CPU time, and the demo's
frames-with-depth and accuracy lines.

    .venv/bin/python tests/bench_demo.py --runs 3 [-- demo options]
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def one_run(extra: list[str]) -> dict:
    """One cold demo; the figures it printed."""
    for folder in ("app", "drivers", "calibration"):
        for path in (ROOT / folder).rglob("*.nb[ic]"):
            path.unlink()
    with tempfile.TemporaryDirectory(prefix="lightflow-cold-") as cache:
        env = dict(os.environ, XDG_CACHE_HOME=cache)
        env.pop("NUMBA_CACHE_DIR", None)
        load = os.getloadavg()
        t0 = time.perf_counter()
        proc = subprocess.run(
            [str(Path(sys.executable).parent / "lightflow"), "demo", "--no-viewer",
             "--out", str(Path(cache) / "out"), *extra],
            env=env, capture_output=True, text=True, cwd=ROOT,
        )  # fmt: skip
        wall = time.perf_counter() - t0
    if proc.returncode != 0:
        sys.exit(f"demo failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    out = proc.stdout
    first = re.search(r"first depth picture after ([\d.]+) s \((\d+) s of CPU", out)
    total = re.search(r"demo took ([\d.]+) s \((\d+) s of CPU", out)
    lines = [ln for ln in out.splitlines()
             if ln.startswith(("frames with depth", "accuracy"))]  # fmt: skip
    return {
        "load_before": load,
        "load_after": os.getloadavg(),
        "first_s": float(first[1]) if first else float("nan"),
        "first_cpu_s": int(first[2]) if first else -1,
        "total_s": float(total[1]) if total else wall,
        "total_cpu_s": int(total[2]) if total else -1,
        "lines": lines,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("extra", nargs="*", help="demo options (after --)")
    args = parser.parse_args()
    for k in range(args.runs):
        r = one_run(args.extra)
        la, lb = r["load_before"], r["load_after"]
        print(f"cold run {k + 1}: first depth picture after {r['first_s']:.1f} s "
              f"({r['first_cpu_s']} s CPU), demo {r['total_s']:.1f} s ({r['total_cpu_s']} s CPU); "
              f"load average before {la[0]:.1f} {la[1]:.1f} {la[2]:.1f}, "
              f"after {lb[0]:.1f} {lb[1]:.1f} {lb[2]:.1f}", flush=True)  # fmt: skip
        for line in r["lines"]:
            print(f"  {line}", flush=True)


if __name__ == "__main__":
    main()
