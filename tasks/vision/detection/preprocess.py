"""Image preprocessing for the coarse search: downsampling, median filter, gamma correction.

All images are 2-D uint8 arrays (rows = v, columns = u, px). The coarse image is the input
reduced by an integer ``factor`` with area averaging; a coarse pixel (uc, vc) covers full-size
pixel centres so that ``u = (uc + 0.5) * factor - 0.5`` (see :func:`coarse_to_full`).
"""

from __future__ import annotations

import cv2
import numpy as np

from tasks.vision.detection.parallel import resize_area


def check_image(image: np.ndarray) -> np.ndarray:
    """Validate a grayscale 8-bit image; raise ValueError with a clear message otherwise."""
    if not isinstance(image, np.ndarray):
        raise ValueError(f"image must be a numpy array, got {type(image).__name__}")
    if image.ndim != 2:
        raise ValueError(f"image must be 2-D grayscale (H, W), got shape {image.shape}")
    if image.dtype != np.uint8:
        raise ValueError(f"image must be uint8, got {image.dtype}")
    if min(image.shape) < 16:
        raise ValueError(f"image too small: {image.shape}")
    return np.ascontiguousarray(image)


def downsample(image: np.ndarray, factor: int) -> np.ndarray:
    """Area-average the image by an integer factor (no-op for 1)."""
    if factor <= 1:
        return image
    return resize_area(image, factor)


def coarse_to_full(uv: np.ndarray, factor: int) -> np.ndarray:
    """Map coarse-image pixel coordinates to full-size ones (px)."""
    return (np.asarray(uv, dtype=float) + 0.5) * factor - 0.5


def full_to_coarse(uv: np.ndarray, factor: int) -> np.ndarray:
    """Map full-size pixel coordinates to coarse-image ones (px); the inverse of :func:`coarse_to_full`."""
    return (np.asarray(uv, dtype=float) + 0.5) / factor - 0.5


def gamma_lut(gamma: float, lo: float, hi: float, toe: float = 0.05) -> np.ndarray:
    """256-entry LUT: stretch [lo, hi] to x in [0, 1], apply a gamma curve, back to 0..255.

    The curve ((x + toe)^γ − toe^γ) / ((1 + toe)^γ − toe^γ) is a gamma with a linear toe: a
    pure x^γ (γ < 1) has an unbounded slope at 0, which turns one grey level of sensor noise in
    a dark dot into a jump of dozens of levels and fake edges.
    """
    x = np.clip((np.arange(256, dtype=float) - lo) / max(hi - lo, 1.0), 0.0, 1.0)
    y = ((x + toe) ** gamma - toe**gamma) / ((1 + toe) ** gamma - toe**gamma)
    return np.round(255.0 * y).astype(np.uint8)


def auto_gamma(image: np.ndarray, median_ksize: int = 3, target_mid: float = 0.5,
               small_tails: bool = False) -> tuple[np.ndarray, dict]:
    """Median filter, then a contrast stretch and gamma that maps the mid-grey level to ``target_mid``.

    The stretch uses the 1st and 99th percentiles (with ``small_tails``, the far tails where
    :func:`keep_small_tails` says so); mid is the Otsu threshold between the dark and the light grey levels and
    γ = log(target_mid) / log(mid) (within [0.5, 2]), so that dark-side and light-side edges get
    comparable strength under uneven illumination and low contrast.
    Returns (image uint8, info dict with lo, hi, gamma and ``tails_differ``: whether
    :func:`keep_small_tails` would change the stretch).
    """
    med = cv2.medianBlur(image, median_ksize) if median_ksize > 1 else image
    hist = cv2.calcHist([med], [0], None, [256], [0, 256]).ravel()
    cdf = np.cumsum(hist) / max(hist.sum(), 1.0)
    lo = float(np.searchsorted(cdf, 0.01))
    hi = float(np.searchsorted(cdf, 0.99))
    wide = keep_small_tails(cdf, lo, hi)
    differ = wide != (lo, hi)
    if small_tails:
        lo, hi = wide
    if hi - lo < 1:
        return med, {"lo": lo, "hi": hi, "gamma": 1.0, "tails_differ": differ}
    mid = _otsu(hist)
    m = np.clip((mid - lo) / (hi - lo), 0.05, 0.95)
    gamma = float(np.clip(np.log(target_mid) / np.log(m), 0.5, 2.0))
    out = cv2.LUT(med, gamma_lut(gamma, lo, hi))
    return out, {"lo": lo, "hi": hi, "gamma": gamma, "tails_differ": differ}


TAIL_FRACTION = 1e-4
"""Fraction of the pixels beyond which a grey level counts as present (a few hot pixels that survive
the median filter do not)."""


def keep_small_tails(cdf: np.ndarray, lo: float, hi: float) -> tuple[float, float]:
    """The stretch's (lo, hi) grey levels, widened to the 0.01 % and 99.99 % levels of ``cdf`` (256,)
    where those lie more than half the stretched range beyond the 1 % and 99 % levels ``lo``, ``hi``.

    A small grid on a large sheet (12 dots of 19 px on a 2560 × 2160 white page: 0.07 % of the
    pixels) puts its dots below the 1st percentile: stretched from the paper's noise, the dots
    clip to black and a faint halo around them becomes the strongest edge (circles found twice
    the dots' size). Where the dots make more than 1 % of the image, as on every campaign view,
    the tails lie within the range and nothing changes. Where they differ, the coarse search
    searches the band again with them and keeps the better of the two grids
    (:class:`tasks.vision.detection.framework.BandSearch`).
    """
    lo_tail = float(np.searchsorted(cdf, TAIL_FRACTION))
    hi_tail = float(np.searchsorted(cdf, 1.0 - TAIL_FRACTION))
    span = hi - lo
    return (lo_tail if lo - lo_tail > 0.5 * span else lo), (hi_tail if hi_tail - hi > 0.5 * span else hi)


def _otsu(hist: np.ndarray) -> float:
    """Otsu threshold (grey level) of a 256-bin histogram."""
    p = hist / max(hist.sum(), 1.0)
    levels = np.arange(256, dtype=float)
    w0 = np.cumsum(p)
    mu = np.cumsum(p * levels)
    with np.errstate(divide="ignore", invalid="ignore"):
        between = (mu[-1] * w0 - mu) ** 2 / (w0 * (1.0 - w0))
    between = np.nan_to_num(between, nan=0.0, posinf=0.0)
    return float(np.argmax(between)) + 0.5


LOG_TOE_DN = 4.0
"""Grey levels added before the logarithm: one level of sensor noise in a black dot stays a small step."""


def log_stretch(image: np.ndarray, median_ksize: int = 3) -> np.ndarray:
    """Median filter, then ln(grey + :data:`LOG_TOE_DN`) stretched from its 1st to its 99th percentile to
    0–255 (uint8, same shape).

    A cast shadow multiplies the dots and the sheet on one side of its edge by the same factor f: on
    this scale the edge is a step of ln f everywhere and every dot's rim a step of ln(ink / sheet) on
    either side, where the gamma of :func:`auto_gamma`, set by the lit sheet, leaves the shadowed dots
    a fifth of the lit ones' contrast (f = 0.35)."""
    med = cv2.medianBlur(image, median_ksize) if median_ksize > 1 else image
    table = np.log(np.arange(256, dtype=float) + LOG_TOE_DN)
    hist = cv2.calcHist([med], [0], None, [256], [0, 256]).ravel()
    cdf = np.cumsum(hist) / max(hist.sum(), 1.0)
    lo, hi = table[int(np.searchsorted(cdf, 0.01))], table[min(int(np.searchsorted(cdf, 0.99)), 255)]
    lut = np.round(255.0 * np.clip((table - lo) / max(hi - lo, 1e-6), 0.0, 1.0)).astype(np.uint8)
    return cv2.LUT(med, lut)
