"""The ``graycode/1`` sequence of formats.md section 4: generation and per-pixel decoding.

For a projector ``W`` x ``H`` pixels, with ``nx = ceil(log2(W))`` and
``ny = ceil(log2(H))``, the frames are: all white; all black; for each column
bit ``b = nx-1 .. 0`` the pattern and its inverse; then the same for the row
bits.  In the column pattern of bit ``b`` projector pixel ``(x, y)`` is white
when bit ``b`` of ``x ^ (x >> 1)`` is 1.

Decoding compares each pattern with its inverse (so it needs no threshold and
is unbiased at stripe edges) and masks pixels that the projector does not
light well (shadow or low contrast between the all-white and all-black frames).
Because neighbouring Gray codes differ in one bit, a camera pixel that straddles
a stripe edge decodes to one of the two neighbouring columns, never further off.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np

SEQUENCE = "graycode/1"


def bit_counts(width: int, height: int) -> tuple[int, int]:
    """``(nx, ny)``: the number of column and row bits for a projector."""
    return max(1, math.ceil(math.log2(width))), max(1, math.ceil(math.log2(height)))


def frame_count(width: int, height: int) -> int:
    """Frames per projector and pose: ``2 + 2 (nx + ny)``."""
    nx, ny = bit_counts(width, height)
    return 2 + 2 * (nx + ny)


def frame_labels(width: int, height: int) -> list[str]:
    """Human-readable names of the frames in sequence order (for error messages)."""
    nx, ny = bit_counts(width, height)
    labels = ["all white", "all black"]
    for axis, n in (("column", nx), ("row", ny)):
        for b in range(n - 1, -1, -1):
            labels += [f"{axis} bit {b}", f"{axis} bit {b} inverse"]
    return labels


def gray_bits(n: int, bit: int) -> np.ndarray:
    """``(n,)`` bool: bit ``bit`` of the Gray code ``i ^ (i >> 1)`` of ``i = 0 .. n-1``."""
    i = np.arange(n, dtype=np.int64)
    return ((i ^ (i >> 1)) >> bit) & 1 == 1


def graycode_images(width: int, height: int) -> Iterator[np.ndarray]:
    """Yield the ``graycode/1`` frames of a projector in order.

    Parameters
    ----------
    width, height : int
        Projector resolution.

    Yields
    ------
    numpy.ndarray
        ``(height, width)`` ``uint8`` images, 0 (black) or 255 (white).
    """
    nx, ny = bit_counts(width, height)
    yield np.full((height, width), 255, np.uint8)
    yield np.zeros((height, width), np.uint8)
    for b in range(nx - 1, -1, -1):
        row = np.where(gray_bits(width, b), 255, 0).astype(np.uint8)
        img = np.broadcast_to(row[None, :], (height, width))
        yield np.ascontiguousarray(img)
        yield np.ascontiguousarray(255 - img)
    for b in range(ny - 1, -1, -1):
        col = np.where(gray_bits(height, b), 255, 0).astype(np.uint8)
        img = np.broadcast_to(col[:, None], (height, width))
        yield np.ascontiguousarray(img)
        yield np.ascontiguousarray(255 - img)


@dataclass(frozen=True)
class Decoded:
    """Result of decoding one projector's sequence seen by the camera.

    Attributes
    ----------
    proj : numpy.ndarray
        ``(h, w, 2)`` float32 projector pixel ``(x, y)`` lighting each camera
        pixel (integer values: the projector pixel whose centre is nearest).
    valid : numpy.ndarray
        ``(h, w)`` bool: lit with enough contrast and decoded inside the projector.
    white, black : numpy.ndarray
        ``(h, w)`` float32 all-white and all-black frames.
    """

    proj: np.ndarray
    valid: np.ndarray
    white: np.ndarray
    black: np.ndarray


def decode_graycode(
    frames: Iterable[np.ndarray],
    width: int,
    height: int,
    min_contrast: float = 8.0,
    min_relative_contrast: float = 0.05,
) -> Decoded:
    """Decode camera frames of one projector's ``graycode/1`` sequence.

    Frames are consumed one at a time, so an iterator that loads them lazily
    keeps memory low.

    Parameters
    ----------
    frames : iterable of numpy.ndarray
        ``2 + 2 (nx + ny)`` grey camera images ``(h, w)`` in sequence order
        (any numeric dtype; 8-bit scale is assumed for ``min_contrast``).
    width, height : int
        Projector resolution.
    min_contrast : float
        Minimum white minus black difference (grey levels) to accept a pixel.
    min_relative_contrast : float
        Minimum ``(white - black) / white``: rejects pixels lit mostly by
        ambient light.

    Returns
    -------
    Decoded
        Projector coordinates per camera pixel and a validity mask.

    Raises
    ------
    ValueError
        If the number of frames is not ``2 + 2 (nx + ny)``.
    """
    nx, ny = bit_counts(width, height)
    expected = 2 + 2 * (nx + ny)
    it = iter(frames)
    got = 0

    def take() -> np.ndarray:
        nonlocal got
        try:
            im = next(it)
        except StopIteration:
            raise ValueError(f"expected {expected} frames for a {width}x{height} projector, "
                             f"got {got}") from None
        got += 1
        return np.asarray(im, np.float32)

    white, black = take(), take()
    contrast = white - black
    valid = (contrast >= min_contrast) & (contrast >= min_relative_contrast * white)
    coords = []
    for n_bits in (nx, ny):
        value = np.zeros(white.shape, np.int32)
        bit = np.zeros(white.shape, bool)
        for _ in range(n_bits):
            bit ^= take() > take()  # binary bit = previous binary bit XOR this Gray bit
            value = (value << 1) | bit
        coords.append(value)
    if next(it, None) is not None:
        raise ValueError(f"expected {expected} frames for a {width}x{height} projector, got more")
    x, y = coords
    valid &= (x < width) & (y < height)
    proj = np.stack([x, y], axis=-1).astype(np.float32)
    return Decoded(proj, valid, white, black)
