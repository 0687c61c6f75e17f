"""The median of a handful of values inside numba kernels, shared by the core's modules."""

from __future__ import annotations

import numba as nb
import numpy as np

from .kernel_options import INTERNAL


@nb.njit(cache=True, error_model="numpy", **INTERNAL)
def median_in_place(values, n):
    """``np.median(values[:n])`` for ``n >= 1`` values, sorting them in place by insertion.

    The same bits as numba's median (the same middle value, or the mean of the same two),
    NaN where a value is NaN, but no copy of the values per call (the triangulation takes
    one for each of 25 candidate pairs per pair of runs) and no partition kernel to
    compile (a second of a first run).
    """
    for i in range(n):
        if np.isnan(values[i]):
            return np.nan
    for i in range(1, n):
        v = values[i]
        j = i - 1
        while j >= 0 and values[j] > v:
            values[j + 1] = values[j]
            j -= 1
        values[j + 1] = v
    h = n >> 1
    return values[h] if n & 1 else 0.5 * (values[h - 1] + values[h])
