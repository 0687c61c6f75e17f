"""Fixtures shared by the test modules.

The suite uses a private cache folder (depth tables, blur tables, numba
kernels), never the user's ``~/.cache/lightflow``: it is set here, before any
test module imports lightflow, and inherited by the subprocesses tests start.
``LIGHTFLOW_TEST_CACHE`` names a folder to reuse between runs (a developer's
shortcut; CI starts empty, as a new machine does).
"""

from __future__ import annotations

import os
import shutil
import tempfile

import pytest
from aravis_sim import Simulator, private_netns_problem

_REUSED = os.environ.get("LIGHTFLOW_TEST_CACHE")
_CACHE = _REUSED or tempfile.mkdtemp(prefix="lightflow-test-cache-")
os.environ["XDG_CACHE_HOME"] = _CACHE
os.environ.pop("NUMBA_CACHE_DIR", None)  # lightflow keys it inside the private cache


def pytest_sessionfinish(session, exitstatus):
    if not _REUSED:
        shutil.rmtree(_CACHE, ignore_errors=True)


@pytest.fixture(scope="module")
def netns():
    """Fail (not skip) unless the test runs in a private network namespace."""
    problem = private_netns_problem()
    if problem:
        pytest.fail(problem)


@pytest.fixture
def sim(netns):
    """Aravis's GigE Vision simulator on loopback, stopped by PID afterwards."""
    with Simulator() as simulator:
        yield simulator
