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
