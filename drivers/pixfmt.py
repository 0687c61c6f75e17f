"""GenICam pixel formats: significant bits, and unpacking of packed 10/12-bit data.

Two packings exist for 10- and 12-bit samples:

- PFNC "p" formats (``Mono10p``, ``Mono12p``, ``BayerRG12p`` ...): samples
  packed LSB first into a continuous little-endian bit stream (4 samples in 5
  bytes at 10 bits, 2 in 3 bytes at 12 bits).
- GigE Vision "Packed" formats (``Mono10Packed``, ``Mono12Packed``,
  ``BayerRG12Packed`` ...): 2 samples in 3 bytes, the high bits of each sample
  in its own byte and both samples' low bits shared in the middle byte.

Unpacking is vectorised numpy; the result holds the raw values (0..1023 or
0..4095) in ``uint16``, and :func:`significant_bits` says what full scale is.
"""

from __future__ import annotations

import re

import numpy as np

_BITS = re.compile(r"^(?:Mono|Bayer(?:RG|GR|GB|BG)|RGB)(8|10|12|14|16)(p|Packed)?$")


def significant_bits(name: str) -> int | None:
    """Bits per sample of a GenICam pixel format (``Mono12`` -> 12), None if unknown."""
    m = _BITS.match(name)
    if m is None:
        return 8 if name == "RGB8Packed" else None
    return int(m.group(1))


def packing(name: str) -> str | None:
    """``"pfnc"`` for the ``...p`` formats, ``"gige"`` for ``...Packed``, else None."""
    if name == "RGB8Packed":
        return None  # an old name of RGB8, not a bit packing
    m = _BITS.match(name)
    if m is None or m.group(2) is None:
        return None
    return "pfnc" if m.group(2) == "p" else "gige"


def packed_row_bytes(width: int, bits: int, kind: str) -> int:
    """Bytes of one packed row of ``width`` samples."""
    if kind == "gige":
        return (width + 1) // 2 * 3
    return (width * bits + 7) // 8


def unpack(rows: np.ndarray, width: int, bits: int, kind: str) -> np.ndarray:
    """Unpack ``(height, row_bytes)`` uint8 rows into ``(height, width)`` uint16 samples.

    Parameters
    ----------
    rows : numpy.ndarray
        The packed image, one row per line (row padding already removed).
    width : int
        Samples per row.
    bits : int
        10 or 12.
    kind : str
        ``"pfnc"`` or ``"gige"`` (see the module docstring).
    """
    if bits not in (10, 12) or kind not in ("pfnc", "gige"):
        raise ValueError(f"no unpacking for {bits}-bit {kind} data")
    h = rows.shape[0]
    b = rows.astype(np.uint16)
    if kind == "gige" or bits == 12:
        n = (width + 1) // 2
        if b.shape[1] < n * 3:  # an odd width's last group may be cut short
            b = np.pad(b, ((0, 0), (0, n * 3 - b.shape[1])))
        g = b[:, : n * 3].reshape(h, n, 3)
        b0, b1, b2 = g[..., 0], g[..., 1], g[..., 2]
        out = np.empty((h, n, 2), np.uint16)
        if kind == "pfnc":  # 12p: p0 = B0 | (B1 & 0xF) << 8, p1 = B1 >> 4 | B2 << 4
            out[..., 0] = b0 | (b1 & 0xF) << 8
            out[..., 1] = b1 >> 4 | b2 << 4
        elif bits == 12:  # Mono12Packed: high bits in B0/B2, low nibbles in B1
            out[..., 0] = b0 << 4 | (b1 & 0xF)
            out[..., 1] = b2 << 4 | b1 >> 4
        else:  # Mono10Packed: low 2 bits at B1[1:0] and B1[5:4]
            out[..., 0] = b0 << 2 | (b1 & 0x3)
            out[..., 1] = b2 << 2 | (b1 >> 4 & 0x3)
        return out.reshape(h, n * 2)[:, :width]
    # 10p: 4 samples in 5 bytes, LSB first
    n = (width + 3) // 4
    need = n * 5
    if b.shape[1] < need:
        b = np.pad(b, ((0, 0), (0, need - b.shape[1])))
    g = b[:, :need].reshape(h, n, 5)
    out = np.empty((h, n, 4), np.uint16)
    out[..., 0] = g[..., 0] | (g[..., 1] & 0x3) << 8
    out[..., 1] = g[..., 1] >> 2 | (g[..., 2] & 0xF) << 6
    out[..., 2] = g[..., 2] >> 4 | (g[..., 3] & 0x3F) << 4
    out[..., 3] = g[..., 3] >> 6 | g[..., 4] << 2
    return out.reshape(h, n * 4)[:, :width]


def pack(samples: np.ndarray, bits: int, kind: str) -> np.ndarray:
    """The inverse of :func:`unpack` (for tests and simulators)."""
    s = samples.astype(np.uint32)
    h, w = s.shape
    if kind == "gige" or bits == 12:
        if w % 2:
            s = np.pad(s, ((0, 0), (0, 1)))
        p0, p1 = s[:, 0::2], s[:, 1::2]
        g = np.empty((h, p0.shape[1], 3), np.uint32)
        if kind == "pfnc":
            g[..., 0] = p0 & 0xFF
            g[..., 1] = (p0 >> 8) | (p1 & 0xF) << 4
            g[..., 2] = p1 >> 4
        elif bits == 12:
            g[..., 0] = p0 >> 4
            g[..., 1] = (p0 & 0xF) | (p1 & 0xF) << 4
            g[..., 2] = p1 >> 4
        else:
            g[..., 0] = p0 >> 2
            g[..., 1] = (p0 & 0x3) | (p1 & 0x3) << 4
            g[..., 2] = p1 >> 2
        return g.reshape(h, -1).astype(np.uint8)
    pad = (-w) % 4
    s = np.pad(s, ((0, 0), (0, pad))).reshape(h, -1, 4)
    word = s[..., 0] | s[..., 1] << 10 | s[..., 2] << 20 | s[..., 3].astype(np.uint64) << 30
    word = word.astype(np.uint64)
    g = np.stack([(word >> (8 * k)) & 0xFF for k in range(5)], axis=-1)
    return g.reshape(h, -1)[:, : packed_row_bytes(w, 10, "pfnc")].astype(np.uint8)
