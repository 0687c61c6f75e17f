"""Line intervals with the projector's whole-column line positions taken out (snapping.py)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lightflow.app.core.bands import BAND_PERIODIC, F_CENTRE, F_INTERVAL, F_VALID, N_FIELDS
from lightflow.app.core.patterns import line_centres, line_footprints
from lightflow.app.core.pipeline import DepthPipeline, PipelineConfig
from lightflow.app.core.rig import Pattern, resolve_rig
from lightflow.app.core.snapping import (
    MIN_SPACINGS,
    LineSnapping,
    column_direction,
    desnap_intervals,
)

WIDTH = 1280
PITCH = 25.82  # most neighbours 26 columns apart, every fifth or sixth 25
PATTERN = Pattern(channel="blue", kind="uniform", width_px=3.0, pitch_px=PITCH, offset_px=0.0)


def _rows(centres, rows=9, noise=0.05):
    """A band table: the same lines in ``rows`` rows, each band's interval the mean of its
    two spacings (one-sided at the ends, as the detector measures them)."""
    n = centres.size
    bands = np.full((rows, n + 4, N_FIELDS), np.nan)
    counts = np.full(rows, n, np.int64)
    rng = np.random.default_rng(3)
    for r in range(rows):
        c = centres + rng.normal(0.0, noise, n)  # centre noise, camera px
        bands[r, :n, F_CENTRE] = c
        bands[r, :n, F_VALID] = 1.0
        d = np.diff(c)
        bands[r, 1 : n - 1, F_INTERVAL] = 0.5 * (d[:-1] + d[1:])
        bands[r, 0, F_INTERVAL] = 1.5 * d[0] - 0.5 * d[1]
        bands[r, n - 1, F_INTERVAL] = 1.5 * d[-1] - 0.5 * d[-2]
    return bands, counts


def _camera(u):
    """Projector column -> camera column of a tilted plane: magnification 0.8 to 1.1."""
    return 40.0 + 0.8 * u + 1.2e-4 * u * u


def _true_intervals(u):
    return (0.8 + 2.4e-4 * u) * PITCH


@pytest.mark.parametrize("first", [3, 11, 20])
@pytest.mark.parametrize("noise", [0.0, 0.05])
def test_intervals_of_whole_column_lines_come_out_right(first, noise):
    lit = line_footprints(PATTERN, WIDTH).mean(axis=1)  # where the lines really are
    nominal = line_centres(PATTERN, WIDTH)
    k = np.arange(first, first + 30)
    bands, counts = _rows(_camera(lit[k]), noise=noise)
    truth = _true_intervals(nominal[k])
    before = np.abs(bands[:, :30, F_INTERVAL] / truth - 1)
    fixed = desnap_intervals(bands, counts, LineSnapping.of(PATTERN, WIDTH, 1, bands.shape[1]))
    after = np.abs(bands[:, :30, F_INTERVAL] / truth - 1)
    assert fixed == 9  # every row's run
    # spacings of 25 and 26 columns read as 25.82: 1.3 % (p90) as measured
    assert np.percentile(before[:, 1:-1], 90) > 0.01
    if noise == 0.0:
        assert after.max() < 0.0003  # measured 0.013 %
    else:
        # 0.05 px of centre noise alone: measured 0.1 % (median) and 0.21-0.24 % (p90)
        assert np.median(after) < 0.0015
        assert np.percentile(after[:, 1:-1], 90) < 0.003


def test_lines_drawn_at_their_nominal_centres_keep_their_intervals():
    k = np.arange(5, 35)
    bands, counts = _rows(_camera(line_centres(PATTERN, WIDTH)[k]))
    before = bands[:, :, F_INTERVAL].copy()
    fixed = desnap_intervals(bands, counts, LineSnapping.of(PATTERN, WIDTH, 1, bands.shape[1]))
    assert fixed <= 1
    assert np.nanmax(np.abs(bands[:, :, F_INTERVAL] / before - 1)) < 0.002


@pytest.mark.parametrize("spacings", [MIN_SPACINGS - 1, MIN_SPACINGS])
def test_only_runs_long_enough_are_corrected(spacings):
    lit = line_footprints(PATTERN, WIDTH).mean(axis=1)
    bands, counts = _rows(_camera(lit[7 : 8 + spacings]))
    before = bands[:, :, F_INTERVAL].copy()
    fixed = desnap_intervals(bands, counts, LineSnapping.of(PATTERN, WIDTH, 1, bands.shape[1]))
    assert fixed == (9 if spacings >= MIN_SPACINGS else 0)
    if spacings < MIN_SPACINGS:
        assert np.array_equal(bands[:, :, F_INTERVAL], before, equal_nan=True)


def test_intervals_the_detector_did_not_take_from_both_spacings_are_left_alone():
    # a periodic run's interval (its median spacing, which its sweep was read with),
    # or one taken from one side of a depth edge: not the mean of the two spacings
    lit = line_footprints(PATTERN, WIDTH).mean(axis=1)
    bands, counts = _rows(_camera(lit[3:33]), noise=0.0)
    bands[:, 10, F_VALID] = BAND_PERIODIC
    bands[:, 20, F_INTERVAL] = 21.0
    before = bands[:, :, F_INTERVAL].copy()
    desnap_intervals(bands, counts, LineSnapping.of(PATTERN, WIDTH, 1, bands.shape[1]))
    assert np.array_equal(bands[:, [10, 20], F_INTERVAL], before[:, [10, 20]])
    assert not np.array_equal(bands[:, 15, F_INTERVAL], before[:, 15])


def test_whole_pitches_and_lines_cut_by_the_projector_edge_need_nothing():
    # a whole pitch: every line on its nominal centre except the first, which the
    # projector's edge cuts in half (columns 0 and 1 for a centre at 0)
    whole = Pattern(channel="blue", kind="uniform", width_px=3.0, pitch_px=18.0, offset_px=0.0)
    assert LineSnapping.of(whole, WIDTH, 1, 160) is None
    assert LineSnapping.of(PATTERN, WIDTH, 1, 1) is None
    assert LineSnapping.of(PATTERN, WIDTH, 1, 160) is not None
    rig = resolve_rig("two-projector")
    assert DepthPipeline(rig, PipelineConfig())._snapping == [None, None]


def test_it_can_be_turned_off():
    rig = resolve_rig("single-projector")
    assert all(s is not None for s in DepthPipeline(rig, PipelineConfig())._snapping)
    off = DepthPipeline(rig, PipelineConfig(whole_columns=False))._snapping
    assert off == [None, None]


def test_a_band_table_wider_than_the_tables_is_refused():
    bands, counts = _rows(_camera(np.arange(10) * PITCH), rows=2)
    with pytest.raises(ValueError, match="bands per row"):
        desnap_intervals(bands, counts, LineSnapping.of(PATTERN, WIDTH, 1, 8))


def test_lines_met_in_decreasing_column_order_are_read_backwards():
    # a projector upside down: along the camera row the lines come last to first
    lit = line_footprints(PATTERN, WIDTH).mean(axis=1)
    nominal = line_centres(PATTERN, WIDTH)
    k = np.arange(40, 10, -1)
    bands, counts = _rows(_camera(WIDTH - lit[k]), noise=0.0)
    truth = _true_intervals(WIDTH - nominal[k])
    fixed = desnap_intervals(bands, counts, LineSnapping.of(PATTERN, WIDTH, -1, bands.shape[1]))
    after = np.abs(bands[:, :30, F_INTERVAL] / truth - 1)
    assert fixed == 9
    assert np.percentile(after, 90) < 0.001


def test_columns_run_backwards_for_a_projector_turned_upside_down():
    rig = resolve_rig("two-projector")
    proj, _ = rig.patterns[0]
    assert column_direction(rig.camera, proj, 1.0) == 1
    turn = np.diag([-1.0, -1.0, 1.0])  # half a turn about the projector's axis
    upside_down = dataclasses.replace(proj, R=turn @ proj.R, t=turn @ proj.t)
    assert column_direction(rig.camera, upside_down, 1.0) == -1


@pytest.mark.parametrize("kind", ["exp2", "exp2-reversed"])
def test_an_exp2_patterns_intervals_come_out_right(kind):
    # its spacings grow from line to line, and whole columns put them 1-5 % off
    pattern = Pattern(channel="red", kind=kind, width_px=3.0, lines=50)
    lit = line_footprints(pattern, WIDTH).mean(axis=1)
    nominal = line_centres(pattern, WIDTH)
    k = np.arange(12, 40)
    bands, counts = _rows(_camera(lit[k]), noise=0.0)
    # the true interval: the camera's slope times the pattern's local nominal spacing
    local = np.gradient(nominal)[k]
    truth = (0.8 + 2.4e-4 * nominal[k]) * local
    before = np.abs(bands[:, : k.size, F_INTERVAL] / truth - 1)
    fixed = desnap_intervals(bands, counts, LineSnapping.of(pattern, WIDTH, 1, bands.shape[1]))
    after = np.abs(bands[:, : k.size, F_INTERVAL] / truth - 1)
    assert fixed == 9
    assert np.percentile(before[:, 1:-1], 90) > 0.01  # measured 1.2 %
    assert np.percentile(after[:, 1:-1], 90) < 0.0003  # measured 0.01 %


def test_the_command_line_can_turn_it_off():
    from argparse import ArgumentParser

    from lightflow.app.options import add_pipeline_options, pipeline_config

    parser = ArgumentParser()
    add_pipeline_options(parser)
    assert pipeline_config(parser.parse_args([])).whole_columns
    assert not pipeline_config(parser.parse_args(["--whole-columns", "off"])).whole_columns
