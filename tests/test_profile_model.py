"""The blur fit's per-band root search: one kernel, the values of the table lookups."""

import numpy as np

from lightflow.app.core.profile_model import (
    S_AXIS,
    _interpolate_root,
    _ramp_roots,
    _ramp_sigma,
    _sigma_grid,
    tables,
)


def test_the_roots_of_the_kernel_are_those_of_the_lookups_over_the_whole_grid():
    t = tables()
    rng = np.random.default_rng(5)
    n = 3000
    line = rng.uniform(2.0, 8.0, n)
    L = rng.uniform(0.0, 20.0, n)
    sigma = rng.uniform(0.4, 2.5, n)
    m = t.measured_width(L, line, sigma) + rng.normal(0.0, 0.1, n)
    r = t.ramp(L, line, sigma) + rng.normal(0.0, 0.1, n)
    m[::50] = np.nan  # and some bands without a width
    want = _ramp_sigma(lambda sg: t.ramp(t.true_length(m, line, sg), line, sg) - r)
    sig = _sigma_grid()
    j, r0, r1 = np.empty(n, np.int64), np.empty(n), np.empty(n)
    _ramp_roots(t.inverse, t.r, S_AXIS, sig, m, line, r, j, r0, r1)
    cols = np.flatnonzero(j > 0)
    got = _interpolate_root(sig, cols, j[cols], r0[cols], r1[cols])
    assert 0.5 * n < want[0].size < n  # most bands have a root, not all
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
