"""The plain reference of the paper (the benchmark's baseline): flows of one row, its limits."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from lightflow.app.core.depth_model import DepthLUT
from lightflow.app.core.errors import ConfigError
from lightflow.app.core.rig import rig_from_dict
from lightflow.app.reference import binarisation_window, reference_depth, row_flows

RIGS = Path(__file__).resolve().parents[1] / "app" / "rigs"


def bands_row(n, interval, length, phase=0.0, ramp=2.0, bg=20.0, top=200.0):
    """A row of trapezoid bands: ``length`` wide at half height, linear ramps."""
    x = np.arange(n, dtype=np.float64)
    v = np.full(n, bg)
    for c in np.arange(15.0 + phase, n - 15.0, interval):
        d = np.abs(x - c) - 0.5 * length  # 0 at half height
        v = np.maximum(v, bg + (top - bg) * np.clip(0.5 - d / ramp, 0.0, 1.0))
    return v


@pytest.mark.parametrize("interval,length", [(30.0, 12.0), (41.3, 17.0), (40.0, 20.0)])
def test_row_flow_is_band_length_over_interval(interval, length):
    # bands near half the interval put the moving average near half height: the run is the length
    v = bands_row(1600, interval, length, phase=0.37)
    columns = np.arange(400) * 4 + 1.5
    flow = row_flows(v, columns, window_px=int(2 * interval) | 1)
    inner = flow[40:-40]
    assert np.isfinite(inner).all()
    expected = length / interval
    assert np.abs(inner - expected).max() < 0.06 * expected
    assert abs(binarisation_window(np.tile(v, (50, 1))) - 2 * interval) <= 3


def test_short_bands_read_long():
    """The paper's threshold at the local mean cuts short bands low: their flow reads long.

    (The pipeline's detector measures each band at half its own height instead.)
    """
    interval, length = 52.7, 8.5
    flow = row_flows(bands_row(1600, interval, length), np.arange(400) * 4 + 1.5, 105)
    inner = flow[40:-40]
    assert np.isfinite(inner).all()
    assert np.all(inner > 1.1 * length / interval)


def test_row_without_bands_has_no_flow():
    assert np.isnan(row_flows(np.full(800, 30.0), np.arange(200) * 4 + 1.5)).all()


def test_reference_needs_two_projectors():
    rig = rig_from_dict(json.loads((RIGS / "single-projector.json").read_text()))
    lut = DepthLUT(4, np.zeros((2, 2), np.float32), np.zeros((2, 2), np.float32),
                   np.zeros((2, 2, 22), np.float32))  # fmt: skip
    with pytest.raises(ConfigError, match="two-projector"):
        reference_depth(np.zeros((8, 8, 3), np.uint8), rig, lut)
