"""Appearance test of coarse circle candidates: is it a filled dot on a clear surround?

A rim found by the Hough search can be an arc of clutter (a letter, the corner of a box, a
shadow edge): the votes only say that edge pixels lie on a circle. A printed dot is also a
uniform disc of its own grey level on a uniform ring of the plate's, for at least half a dot
radius around it (a plate's gap between dots is at least its radius, pitch ≥ 1.5 diameters).
Grey levels are sampled (bilinear) on ellipses scaled from each candidate's own: inside at
0–0.65 of the axes, outside at 1.3 and 1.5. Inside, samples are compared with the level halfway
between the medians of the two; outside, each with the dot's own level just inside the rim on
the same ray, so that a shadow edge across a dot does not fail it. Units: px of the image the
candidates were found on; angles rad from +u towards +v.
"""

from __future__ import annotations

import warnings

import cv2
import numpy as np

from tasks.vision.detection.stats import masked_median

INNER_SCALES = (0.0, 0.25, 0.45, 0.65)
OUTER_SCALES = (1.3, 1.5)
N_ANGLES = 24


def dot_fill(image: np.ndarray, centres: np.ndarray, axes: np.ndarray, theta: np.ndarray,
             dark_dots: bool) -> tuple[np.ndarray, np.ndarray]:
    """(inside, outside) fractions (K,) of the samples inside the candidate ellipses (centres
    (K, 2), semi-axes (K, 2), angle (K,)) on the dot's side of the halfway threshold, and of the
    samples outside them that step up (down) from the dot on their ray by a third of the dot's
    contrast; samples off the image are left out (a fraction is 1 without samples)."""
    fill_in, fill_out, _ = dot_appearance(image, centres, axes, theta, dark_dots)
    return fill_in, fill_out


def dot_appearance(image: np.ndarray, centres: np.ndarray, axes: np.ndarray, theta: np.ndarray,
                   dark_dots: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`dot_fill`'s (inside, outside) fractions (K,), and the candidates' grey levels (K, 2):
    the median of the samples inside (0–0.65 of the axes) and of those on the ring outside (1.3–1.5),
    in the image's grey levels (NaN without samples)."""
    if len(centres) == 0:
        return np.zeros(0), np.zeros(0), np.zeros((0, 2))
    ang = np.arange(N_ANGLES) * (2 * np.pi / N_ANGLES)
    scales = np.array(INNER_SCALES + OUTER_SCALES)
    ca, sa = np.cos(ang), np.sin(ang)
    ct, st = np.cos(theta)[:, None, None], np.sin(theta)[:, None, None]
    ex = axes[:, 0, None, None] * scales[None, :, None] * ca[None, None, :]  # (K, S, A) ellipse frame
    ey = axes[:, 1, None, None] * scales[None, :, None] * sa[None, None, :]
    u = (centres[:, 0, None, None] + ct * ex - st * ey).astype(np.float32)
    v = (centres[:, 1, None, None] + st * ex + ct * ey).astype(np.float32)
    h, w = image.shape
    inside_img = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    k, s, a = u.shape
    g = cv2.remap(image, u.reshape(k, s * a), v.reshape(k, s * a), cv2.INTER_LINEAR,
                  borderMode=cv2.BORDER_REPLICATE).reshape(k, s, a).astype(float)
    n_in = len(INNER_SCALES)
    rim_in = np.where(inside_img[:, n_in - 1], g[:, n_in - 1], np.nan)  # (K, A) just inside the rim
    g_in = np.where(inside_img[:, :n_in], g[:, :n_in], np.nan).reshape(k, -1)
    g_out3 = np.where(inside_img[:, n_in:], g[:, n_in:], np.nan)  # (K, S_out, A)
    g_out = g_out3.reshape(k, -1)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a candidate with no sample in the image
        m_in = masked_median(g_in, np.isfinite(g_in))  # NaN without samples
        m_out = masked_median(g_out, np.isfinite(g_out))
        thr = 0.5 * (m_in + m_out)[:, None]
        sign = 1.0 if dark_dots else -1.0
        dot_side = sign * (thr - g_in) > 0
        # outside: brighter (darker) than the dot just inside the rim on the same ray, by a third of
        # the dot's contrast: a shadow edge or a light gradient across the dot scales both alike
        step = sign * (g_out3 - rim_in[:, None, :])
        plate_side = (step > (1.0 / 3.0) * sign * (m_out - m_in)[:, None, None]).reshape(k, -1)
        n_i = np.isfinite(g_in).sum(axis=1)
        n_o = np.isfinite(g_out).sum(axis=1)
        fill_in = np.where(n_i > 0, dot_side.sum(axis=1) / np.maximum(n_i, 1), 1.0)
        fill_out = np.where(n_o > 0, plate_side.sum(axis=1) / np.maximum(n_o, 1), 1.0)
    polarity_ok = sign * (m_out - m_in) > 0
    polarity_ok |= ~(np.isfinite(m_in) & np.isfinite(m_out))
    return (np.where(polarity_ok, fill_in, 0.0), np.where(polarity_ok, fill_out, 0.0),
            np.column_stack([m_in, m_out]))
