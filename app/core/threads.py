"""One thread pool shared by the per-frame kernels of the pipeline.

The per-frame numba kernels are serial over a range of rows and release the GIL;
:func:`run_rows` runs bands of rows on a thread per core.  numba's
``parallel=True`` would compile each kernel several times slower (seconds on a
cold cache, on the path to a first depth picture) for the same speed.

The pool is created on first use and shared by every pipeline of the process
(never one per call); it is not part of any pipeline's state, so pickled or
forked pipelines do not carry it: a forked child starts its own.  It has one
thread fewer than the cores, because the calling thread always works too, and a
caller that would wait for a task no pool thread has started yet runs it itself
(:func:`_finish`): nested calls (a band of rows inside a task of
:func:`run_tasks`) never wait behind a busy pool, and never run more threads
than cores.
"""

from __future__ import annotations

import functools
import os
import threading
from concurrent.futures import ThreadPoolExecutor, wait

import cv2

_lock = threading.Lock()
_pool: ThreadPoolExecutor | None = None
_local = threading.local()
_threads: int | None = None


def _mark_worker() -> None:
    _local.worker = True


def _forget_pool() -> None:
    # the parent's threads do not exist in a forked child: start a new pool there
    global _pool
    _pool = None


os.register_at_fork(after_in_child=_forget_pool)


def threads() -> int:
    """Number of threads :func:`run_rows` uses: one per core (``os.cpu_count()``)."""
    global _threads
    if _threads is None:  # asked about ten times per frame: once is enough
        _threads = max(1, os.cpu_count() or 1)
    return _threads


def shared_pool() -> ThreadPoolExecutor:
    """The process's kernel thread pool (one thread fewer than :func:`threads`), created on
    first use."""
    global _pool
    with _lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(max(1, threads() - 1), "lightflow-rows",
                                       initializer=_mark_worker)  # fmt: skip
            # OpenCV's own thread pool would compete with this one for the same cores:
            # its threaded grey closing of a 1600x1200 frame took 2-11 ms on 2 cores,
            # against 1.4 ms on one thread
            cv2.setNumThreads(1)
        return _pool


def run_rows(kernel, n: int, *args) -> None:
    """Run ``kernel(*args, r0, r1)`` over rows ``0 .. n`` in one band per thread.

    The calling thread runs the last band itself.  Bands of rows are
    independent (each row writes only its own outputs), so the result is the
    same as one call over all rows, bit for bit.

    Parameters
    ----------
    kernel : callable
        A jitted kernel that releases the GIL (``nogil=True``) and takes the
        first and one-past-last row as its last two arguments.
    n : int
        Number of rows.
    *args
        The kernel's other arguments.
    """
    t = min(threads(), n)
    if t <= 1 or getattr(_local, "worker", False):
        # one band, or called from a pool thread (waiting on the pool there could deadlock)
        kernel(*args, 0, n)
        return
    edges = [n * b // t for b in range(t + 1)]
    pool = shared_pool()
    calls = [functools.partial(kernel, *args, edges[b], edges[b + 1]) for b in range(t - 1)]
    futures = [pool.submit(c) for c in calls]
    try:
        kernel(*args, edges[t - 1], edges[t])
    except BaseException:
        _settle(futures)
        raise
    _finish(futures, calls)


def run_tasks(*tasks):
    """Run independent callables at once, one per core; return their results in order.

    The calling thread runs the last one itself (and all of them, one after the
    other, on one core or from a pool thread, where waiting on the pool could
    deadlock).  For OpenCV and numba calls that release the GIL.

    Parameters
    ----------
    *tasks : callable
        Functions without arguments.

    Returns
    -------
    list
        ``[task() for task in tasks]``.
    """
    if len(tasks) <= 1 or threads() <= 1 or getattr(_local, "worker", False):
        return [task() for task in tasks]
    pool = shared_pool()
    futures = [pool.submit(task) for task in tasks[:-1]]
    try:
        last = tasks[-1]()
    except BaseException:
        _settle(futures)
        raise
    return [*_finish(futures, tasks[:-1]), last]


def _finish(futures: list, calls) -> list:
    """The results of ``futures`` (of ``calls``); those no pool thread has started yet
    run on this thread (from the last: the pool takes them from the first), instead of
    waiting behind whatever keeps the pool busy (another caller's tasks, or this
    caller's outer task)."""
    done = [None] * len(futures)
    ran = [False] * len(futures)
    try:
        for k in range(len(futures) - 1, -1, -1):
            if futures[k].cancel():
                done[k] = calls[k]()
                ran[k] = True
        return [done[k] if ran[k] else f.result() for k, f in enumerate(futures)]
    except BaseException:
        _settle(futures)
        raise


def _settle(futures: list) -> None:
    """After an exception on the calling thread: tasks not started never start, and
    those running finish before it propagates (they write into the caller's arrays)."""
    for f in futures:
        f.cancel()
    wait(futures)
