"""The blur fits' per-band root search: one kernel, the values of the table lookups."""

import numpy as np
import pytest

from lightflow.app.core.profile_model import S_AXIS, _ramp_sigma, tables


def _roots_by_lookups(m, line, r, still):
    """The root search as it was: the mismatch of every band at every sigma of the grid."""
    t = tables()
    sig = np.arange(S_AXIS[0] + 0.05, S_AXIS[-1], 0.05)
    res = np.stack([
        t.ramp(np.zeros_like(m) if still else t.true_length(m, line, sg), line, sg) - r
        for sg in sig
    ])  # fmt: skip
    pos = np.isfinite(res) & (res >= 0)
    first = np.argmax(pos, axis=0)
    cols = np.flatnonzero(pos.any(axis=0) & (first > 0))
    j = first[cols]
    r0, r1 = res[j - 1, cols], res[j, cols]
    good = np.isfinite(r0) & (r1 > r0)
    cols, j, r0, r1 = cols[good], j[good], r0[good], r1[good]
    return cols, sig[j - 1] + (sig[j] - sig[j - 1]) * (-r0) / (r1 - r0)


@pytest.mark.parametrize("still", [False, True])
def test_the_roots_of_the_kernel_are_those_of_the_lookups_over_the_whole_grid(still):
    t = tables()
    rng = np.random.default_rng(5)
    n = 3000
    line = rng.uniform(2.0, 8.0, n)
    L = np.zeros(n) if still else rng.uniform(0.0, 20.0, n)
    sigma = rng.uniform(0.4, 2.5, n)
    m = t.measured_width(L, line, sigma) + rng.normal(0.0, 0.1, n)
    r = t.ramp(L, line, sigma) + rng.normal(0.0, 0.1, n)
    m[::50] = np.nan  # and some bands without a width
    r[::70] = np.nan
    want = _roots_by_lookups(m, line, r, still)
    got = _ramp_sigma(m, line, r, still=still)
    assert 0.5 * n < want[0].size < n  # most bands have a root, not all
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
