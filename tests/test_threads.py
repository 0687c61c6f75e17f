"""The kernel pool: independent tasks give the serial results."""

from lightflow.app.core.threads import run_tasks, shared_pool


def test_tasks_return_their_results_in_order_also_from_a_pool_thread():
    tasks = [lambda i=i: i * i for i in range(5)]
    assert run_tasks(*tasks) == [0, 1, 4, 9, 16]
    # from a pool thread they run there, one after the other (no wait on the pool)
    assert shared_pool().submit(run_tasks, *tasks).result() == [0, 1, 4, 9, 16]
    assert run_tasks() == []

