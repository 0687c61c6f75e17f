"""The band detector's measurements shipped with the sources (app/core/profile_measured.npz).

A first run (``lightflow demo`` on a new machine) loads them instead of running
the detector on every table cell; this test regenerates them and asserts they
are the same (to 1e-9 px), so that the file cannot go stale after a change to the
detector.
"""

from __future__ import annotations

import numpy as np

from lightflow.app.core.profile_model import MEASURED_PATH, load_measured, measure_tables

REGENERATE = ('.venv/bin/python -c "from lightflow.app.core.profile_model import '
              'write_measured; write_measured()"')  # fmt: skip


def test_shipped_measurements_are_what_the_detector_measures_now():
    shipped_m, shipped_r = load_measured()
    assert shipped_m is not None, f"{MEASURED_PATH} is missing or malformed: {REGENERATE}"
    m, r = measure_tables()
    stale = f"{MEASURED_PATH.name} is stale (the detector changed): {REGENERATE}"
    # identical here; 1e-9 px leaves room for another CPU's last-bit rounding (numba
    # compiles for the machine), while any change to the detector moves cells by far more
    np.testing.assert_allclose(m, shipped_m, rtol=0, atol=1e-9, equal_nan=True, err_msg=stale)
    np.testing.assert_allclose(r, shipped_r, rtol=0, atol=1e-9, equal_nan=True, err_msg=stale)
    # small enough to ship, and mostly finite (the detector measured nearly every cell)
    assert MEASURED_PATH.stat().st_size < 2_000_000
    assert np.isfinite(m).mean() > 0.99 and np.isfinite(r).mean() > 0.99
