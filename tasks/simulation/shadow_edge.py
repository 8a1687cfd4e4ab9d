"""A dot grid with a cast shadow's straight edge across it, with exact truth (px): for the rim fit's tests
and ``bench/bench_shadow_sweep.py``.

Not the project's renderer: the plate faces the camera (no perspective, no lens), each dot is a
disc drawn at 8× and area-averaged, the reflectance (dot and sheet) is multiplied by the shadow's
light factor f + (1 − f) Φ(s / w) (s: signed distance px to the edge, a straight line; w: its
blur), then by the light (220 DN, × ``exposure``, clipped at 255 like a camera), blurred by the
optics (Gaussian σ px) and given Gaussian noise. Frames: image pixels (u right, v down), origin at
the centre of the top-left pixel; the plate's dot order is ``plate.dot_centres_mm()``'s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.special import ndtr

from tasks.machine.plate import DotPlate
from tasks.simulation.detector_stress import ISSUE_PLATE

SUPERSAMPLE = 8


@dataclass(frozen=True)
class ShadowEdgeCase:
    """dot_px: dot diameter; shadow: the light factor in the shadow (1 = none); edge_blur_px: the
    shadow edge's blur w; edge_offset: where the edge passes the grid's centre, along its normal,
    in dot radii; edge_angle_deg: the edge's direction from +u; spin_deg: the plate's in-plane
    turn; optics_sigma_px, noise_dn: the optics' blur and the sensor noise; exposure: light × this
    (above about 1.16 the lit light dots saturate: the image is clipped at 255)."""

    dot_px: float
    dark_dots: bool = True
    shadow: float = 0.35
    edge_blur_px: float = 1.0
    edge_offset: float = 0.0
    edge_angle_deg: float = 70.0
    spin_deg: float = 8.0
    optics_sigma_px: float = 0.7
    noise_dn: float = 2.0
    exposure: float = 1.0
    seed: int = 0
    plate: DotPlate = field(default=ISSUE_PLATE)


def render_shadow_edge(case: ShadowEdgeCase) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(image (H, W) uint8, true dot centres (rows*cols, 2) px, each dot's distance to the shadow's
    edge (rows*cols,) in dot radii)."""
    plate = case.plate
    scale = case.dot_px / plate.dot_diameter_mm  # px / mm
    xy = plate.dot_centres_mm()[:, :2] * scale
    xy[:, 1] *= -1.0  # plate +Y up on screen
    c, s = math.cos(math.radians(case.spin_deg)), math.sin(math.radians(case.spin_deg))
    xy = xy @ np.array([[c, s], [-s, c]])
    margin = 1.5 * plate.pitch_range_mm[0] * scale + 4.0
    lo = xy.min(axis=0) - margin
    size = np.ceil(xy.max(axis=0) - lo + margin).astype(int)
    truth = xy - lo
    w, h = int(size[0]), int(size[1])
    ss = SUPERSAMPLE
    vv, uu = np.mgrid[0 : h * ss, 0 : w * ss].astype(np.float32)
    uu, vv = (uu + 0.5) / ss - 0.5, (vv + 0.5) / ss - 0.5
    radius = case.dot_px / 2
    dots = np.zeros((h * ss, w * ss), np.float32)
    for cu, cv in truth:
        dots = np.maximum(dots, ((uu - cu) ** 2 + (vv - cv) ** 2 <= radius**2).astype(np.float32))
    cover = cv2.resize(dots, (w, h), interpolation=cv2.INTER_AREA)
    ink, paper = 0.14, 1.0
    reflect = (ink * cover + paper * (1 - cover)) if case.dark_dots else (paper * cover + ink * (1 - cover))
    ang = math.radians(case.edge_angle_deg)
    normal = np.array([-math.sin(ang), math.cos(ang)])
    centre = truth.mean(axis=0) + case.edge_offset * radius * normal
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    dist = (u - centre[0]) * normal[0] + (v - centre[1]) * normal[1]
    light = case.shadow + (1.0 - case.shadow) * ndtr(dist / max(case.edge_blur_px, 0.05))
    grey = (220.0 * case.exposure * reflect * light).astype(np.float32)
    if case.optics_sigma_px > 0:
        grey = cv2.GaussianBlur(grey, (0, 0), case.optics_sigma_px)
    rng = np.random.default_rng(case.seed)
    grey = grey + rng.normal(0.0, case.noise_dn, grey.shape)
    to_edge = np.abs((truth - centre) @ normal) / radius
    return np.clip(np.rint(grey), 0, 255).astype(np.uint8), truth, to_edge
