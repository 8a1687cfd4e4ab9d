"""Small statistics shared by the detection stages."""

from __future__ import annotations

import numpy as np


def masked_median(values: np.ndarray, mask: np.ndarray, default: float = np.nan) -> np.ndarray:
    """Median along the last axis of ``values`` where ``mask`` (sort-based; NaN-free, fast)."""
    v = np.sort(np.where(mask, values, np.inf), axis=-1)
    n = mask.sum(axis=-1)
    lo = np.take_along_axis(v, np.maximum((n - 1) // 2, 0)[..., None], axis=-1)[..., 0]
    hi = np.take_along_axis(v, np.maximum(n // 2, 0)[..., None], axis=-1)[..., 0]
    with np.errstate(invalid="ignore"):
        return np.where(n > 0, 0.5 * (lo + hi), default)


def percentile(values: np.ndarray, q: float) -> float:
    """``np.percentile(values, q)`` (linear interpolation) of a non-empty 1-D array, as a float: the two
    order statistics by one partition instead of numpy's general path (several times faster on the
    few thousand pixels of a place's window); the interpolation is numpy's (``b − (b − a)(1 − g)`` from
    g = 0.5 on), so the result has its bits (tests/vision/test_detection_kernels.py)."""
    n = values.size
    at = (n - 1) * (q / 100.0)
    k = int(np.floor(at))
    if k + 1 >= n:
        return float(np.partition(values, k)[k])
    g = at - k
    part = np.partition(values, (k, k + 1))
    lo, hi = part[k], part[k + 1]
    d = hi - lo
    return float(values.dtype.type(hi - d * (1 - g) if g >= 0.5 else lo + d * g))
