"""The band detector's measurements shipped with the sources (app/core/profile_measured.npz).

A first run (``lightflow demo`` on a new machine) loads them instead of running
the detector on every table cell; this test regenerates them and asserts they
are identical, so that the file cannot go stale after a change to the detector.
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
    assert np.array_equal(m, shipped_m, equal_nan=True), stale
    assert np.array_equal(r, shipped_r, equal_nan=True), stale
    # small enough to ship, and mostly finite (the detector measured nearly every cell)
    assert MEASURED_PATH.stat().st_size < 2_000_000
    assert np.isfinite(m).mean() > 0.99 and np.isfinite(r).mean() > 0.99
