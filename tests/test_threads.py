"""The kernel pool: independent tasks give the serial results."""

import threading

import numpy as np

from lightflow.app.core.threads import run_rows, run_tasks, shared_pool


def test_tasks_return_their_results_in_order_also_from_a_pool_thread():
    tasks = [lambda i=i: i * i for i in range(5)]
    assert run_tasks(*tasks) == [0, 1, 4, 9, 16]
    # from a pool thread they run there, one after the other (no wait on the pool)
    assert shared_pool().submit(run_tasks, *tasks).result() == [0, 1, 4, 9, 16]
    assert run_tasks() == []


def test_a_task_that_waits_behind_a_busy_pool_runs_on_the_caller():
    # every pool thread held until the caller's tasks are done: they must not wait for it
    release = threading.Event()
    held = [shared_pool().submit(release.wait) for _ in range(shared_pool()._max_workers)]
    try:
        assert run_tasks(*(lambda i=i: (i, threading.current_thread()) for i in range(3))) == [
            (i, threading.current_thread()) for i in range(3)
        ]
        out = np.zeros(10)
        run_rows(_fill, 10, out)
        assert np.array_equal(out, np.arange(10))
    finally:
        release.set()
    assert all(f.result() for f in held)


def _fill(out, r0, r1):
    out[r0:r1] = np.arange(r0, r1)


def test_a_failing_task_on_the_caller_waits_for_the_running_ones():
    # a task still running on the pool writes into the caller's arrays: the exception
    # reaches the caller only after it has finished
    started = threading.Event()
    finished = []

    def slow():
        started.set()
        threading.Event().wait(0.2)  # the pool thread is busy for a while
        finished.append(True)

    def fail():
        started.wait(5.0)
        raise RuntimeError("boom")

    try:
        run_tasks(slow, fail)
    except RuntimeError as exc:
        assert str(exc) == "boom"
    else:
        raise AssertionError("the caller's exception was lost")
    assert finished == [True]
