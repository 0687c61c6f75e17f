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
