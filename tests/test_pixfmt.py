"""Packed GenICam pixel formats: hand-computed bytes, round trips, conversion to RGB."""

from __future__ import annotations

import numpy as np
import pytest

from lightflow.drivers.aravis import convert_image, supported_format
from lightflow.drivers.pixfmt import pack, packing, significant_bits, unpack


def test_significant_bits_and_packing():
    assert significant_bits("Mono8") == 8
    assert significant_bits("Mono12") == 12
    assert significant_bits("BayerRG12p") == 12
    assert significant_bits("Mono10Packed") == 10
    assert significant_bits("RGB8Packed") == 8
    assert packing("Mono12p") == "pfnc" and packing("Mono12Packed") == "gige"
    assert packing("Mono12") is None and packing("RGB8Packed") is None


def test_hand_packed_bytes():
    # samples 0x123, 0x456 as the standards lay them out
    row = np.array([[0x23, 0x61, 0x45]], np.uint8)  # PFNC Mono12p: LSB first
    assert unpack(row, 2, 12, "pfnc").tolist() == [[0x123, 0x456]]
    row = np.array([[0x12, 0x63, 0x45]], np.uint8)  # GigE Mono12Packed
    assert unpack(row, 2, 12, "gige").tolist() == [[0x123, 0x456]]
    # Mono10p: 0x3FF, 0, 0x155, 0x2AA in 5 bytes, LSB first
    bits = 0x3FF | 0 << 10 | 0x155 << 20 | 0x2AA << 30
    row = np.array([[(bits >> (8 * k)) & 0xFF for k in range(5)]], np.uint8)
    assert unpack(row, 4, 10, "pfnc").tolist() == [[0x3FF, 0, 0x155, 0x2AA]]
    # GigE Mono10Packed: high 8 bits per sample, the two low-bit pairs in the middle byte
    row = np.array([[0xFF, 0x3 | 0x1 << 4, 0x55]], np.uint8)
    assert unpack(row, 2, 10, "gige").tolist() == [[0x3FF, 0x155]]


@pytest.mark.parametrize("bits, kind", [(10, "pfnc"), (12, "pfnc"), (10, "gige"), (12, "gige")])
@pytest.mark.parametrize("width", [8, 7, 13])
def test_round_trip(bits, kind, width):
    rng = np.random.default_rng(width)
    samples = rng.integers(0, 2**bits, (3, width)).astype(np.uint16)
    np.testing.assert_array_equal(unpack(pack(samples, bits, kind), width, bits, kind), samples)


@pytest.mark.parametrize("fmt", ["Mono12p", "Mono12Packed", "Mono10p", "BayerRG12p"])
def test_convert_packed_image(fmt):
    assert supported_format(fmt)
    bits, kind = significant_bits(fmt), packing(fmt)
    rng = np.random.default_rng(1)
    samples = rng.integers(0, 2**bits, (6, 8)).astype(np.uint16)
    padding = 4
    rows = pack(samples, bits, kind)
    data = np.concatenate([rows, np.zeros((6, padding), np.uint8)], axis=1).tobytes()
    rgb = convert_image(data, fmt, 8, 6, row_padding=padding)
    assert rgb.shape == (6, 8, 3) and rgb.dtype == np.uint16
    if fmt.startswith("Mono"):
        np.testing.assert_array_equal(rgb[..., 0], samples)
    else:
        assert rgb.max() < 2**bits
