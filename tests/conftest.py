"""Fixtures shared by the test modules."""

from __future__ import annotations

import pytest
from aravis_sim import Simulator, private_netns_problem


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
