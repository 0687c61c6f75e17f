"""Process memory policy: freed frame-sized buffers are kept for the next frame.

Every frame allocates a few arrays of megabytes (the decoded image, its print-filled
copy, the full-resolution depth and its standard deviation).  glibc's malloc serves
such sizes with ``mmap`` and returns them to the kernel when freed, so the next frame
faults every page in again: on a 2-core VM that cost about 2 us a page, 2-3 ms of
kernel time per 6 MB array.  Raising the ``mmap`` and trim thresholds makes malloc
keep freed blocks in its heap and hand them out again.  The cost is that the process
keeps its peak heap (a few hundred MB) until it exits.

Only the application's entry points call :func:`keep_freed_memory` (the command line,
batch workers): a library must not change its host process's allocator.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

#: ``mallopt`` parameters (glibc's malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
#: blocks up to this size come from the heap (frames are 6-8 MB; glibc caps the value
#: at HEAP_MAX_SIZE / 2 = 32 MB on 64-bit systems)
MMAP_THRESHOLD = 32 << 20
#: free heap above this much is returned to the kernel
TRIM_THRESHOLD = 1 << 30

_done = False


def keep_freed_memory() -> bool:
    """Have glibc's malloc keep freed frame-sized blocks for reuse (once per process).

    Returns
    -------
    bool
        True when the thresholds are set (glibc); False elsewhere (another C
        library, another OS), where nothing changes.
    """
    global _done
    if _done:
        return True
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # musl has no mallopt
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    _done = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(
        mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD)
    )
    return _done
