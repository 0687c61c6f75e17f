"""The camera's response curve: linearising tables and images."""

from __future__ import annotations

import numpy as np
import pytest

from lightflow.app.core.response import LINEAR_FULL, linearise, linearising_table


@pytest.mark.parametrize(
    "dtype, full", [(np.uint8, 255.0), (np.uint16, 4095.0), (np.uint16, 65535.0)]
)
def test_linearising_table_undoes_the_response(dtype, full):
    gamma = 2.2
    table = linearising_table(gamma, np.dtype(dtype), full)
    assert table.dtype == np.uint16 and table.size == (256 if dtype == np.uint8 else 65536)
    light = np.linspace(0.0, 1.0, 50)
    stored = np.round(full * light ** (1 / gamma)).astype(dtype)
    # back to the light within the camera's own rounding (steepest near black)
    back = table[stored] / LINEAR_FULL
    step = gamma * np.maximum(stored / full, 1 / full) ** (gamma - 1) / full
    assert np.all(np.abs(back - light) <= step + 1 / LINEAR_FULL)
    assert table[0] == 0 and table[int(full)] == LINEAR_FULL
    if dtype == np.uint16:
        assert np.all(table[int(full) :] == LINEAR_FULL)  # values past a 12-bit full scale


def test_linearise_maps_every_value_through_the_table():
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (37, 41, 3)).astype(np.uint8)
    table = linearising_table(1.8, image.dtype, 255.0)
    out = linearise(image, table)
    assert out.dtype == np.uint16 and out.shape == image.shape
    assert np.array_equal(out, table[image])


def test_find_gamma_finds_the_root_and_settles_a_linear_camera_at_once():
    from lightflow.app.core.response import LINEAR_SNAP, find_gamma

    calls = []

    def excess_for(gamma_true, lines=5000):
        def excess(log_gamma):
            calls.append(log_gamma)
            # wider lines below the true gamma; too few lines far above it (faint bands)
            return (1.3 * (np.log(gamma_true) - log_gamma), lines if log_gamma < 1.2 else 10)

        return excess

    gamma, measured, lines = find_gamma(excess_for(2.2), 500)
    assert gamma == pytest.approx(2.2, rel=0.005) and measured == pytest.approx(gamma, abs=1e-3)
    assert lines == 5000
    calls.clear()
    gamma, measured, _ = find_gamma(excess_for(1.02), 500)
    assert gamma == 1.0 and measured == pytest.approx(1.02, rel=0.002) and len(calls) == 2
    assert find_gamma(excess_for(1.0 + 2 * LINEAR_SNAP), 500)[0] == pytest.approx(1.1, rel=0.005)
    # too few lines everywhere, or no fall through 0: no answer
    assert find_gamma(excess_for(2.2, lines=100), 500) is None
    assert find_gamma(lambda lg: (0.5, 5000), 500) is None
