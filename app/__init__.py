"""lightflow's application package: the processing core and the application around it.

Importing it keys numba's on-disk kernel cache by the source of lightflow's
jitted modules (see :func:`_key_numba_cache`) and keeps OpenBLAS to one thread.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path


def _key_numba_cache() -> None:
    """Point numba's cache at a folder named by a hash of the jitted modules' source.

    numba checks a cached kernel only against its own file's timestamp, so a
    kernel that calls a jitted function of another module (flow calls
    depth_model, profile_model calls bands) would be served stale after that
    other module changed.  Keying the whole cache by the source of every
    module with kernels makes a change anywhere start a fresh cache.
    ``NUMBA_CACHE_DIR`` set by the user wins.
    """
    if "NUMBA_CACHE_DIR" in os.environ:
        return
    root = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for folder in (root, root.parent / "drivers"):
        for path in sorted(folder.rglob("*.py")):
            digest.update(str(path.relative_to(folder)).encode())
            digest.update(path.read_bytes())
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "lightflow"
    os.environ["NUMBA_CACHE_DIR"] = str(cache / f"numba-{digest.hexdigest()[:16]}")


_key_numba_cache()

# lightflow's matrices are small and its kernels run on their own thread per core
# (core/threads.py): OpenBLAS's threads only spin-wait beside them, a few per cent of
# the CPU of a replay.  Effective when lightflow is imported before numpy; the
# user's setting wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
