"""Stress images for the dot-grid detectors: our renderer, then what real photographs add.

:func:`render_stress_case` renders a plate with :func:`tasks.simulation.render.render_plate_image` (lens
distortion, defocus, vignetting, illumination gradient, noise) and then adds, as a case asks,
what a phone or webcam photograph of a printed sheet has and our campaign renders do not: paper
texture, a cluttered background (lines, text, boxes, dot-like blobs, a blotchy texture like
foliage) around the sheet, a soft shadow across the plate, a colour cast with chroma noise, JPEG
compression, and the conversion back to 8-bit grey (``cv2.COLOR_BGR2GRAY``, as ``fivecal
detect`` reads a colour file). Ground truth is :func:`tasks.simulation.render.true_dot_centres` (the
projected 3-D dot centres, distortion included).

:data:`STRESS_CASES` is the named set the tests and ``bench/bench_stress.py`` run: large dots
on a 12 MP photograph (one before a busy, sunlit background), a fisheye webcam frame, small
distant dots, 50° of perspective, uneven light, both polarities. Frames: image px (u right,
v down); plate mm as in :mod:`tasks.machine.plate`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from scipy.spatial import cKDTree

from tasks.machine.camera_model import CameraModel
from tasks.machine.distortion import project_points_ext
from tasks.machine.plate import DotPlate, facing_camera_pose
from tasks.simulation.render import (
    ImagingConditions,
    plate_in_view,
    render_plate_image,
    true_dot_centres,
)

ISSUE_PLATE = DotPlate(4, 3, 6.0, 4.0, dark_dots=True, margin_mm=5.0, name="stress")
"""The sheet of the issue's photographs: 4 × 3 dots of Ø 4 mm at a 6 mm pitch, on paper."""


@dataclass(frozen=True)
class StressCase:
    """One stress image. Lengths in px of the output image, angles in degrees.

    dot_px: dot diameter in the image centre; focal_px: focal length (px, square pixels);
    tilt_deg / tilt_azimuth_deg: plate tilt and the direction of its axis; spin_deg: in-plane
    turn; offset: plate centre as a fraction of the image half-size (u, v), for distortion;
    k1, k2: radial distortion (OpenCV model; strong barrel ≈ −0.35, 0.1); clutter: items drawn
    around the sheet; texture: background blotches and paper grain; shadow: darkest factor of a
    soft shadow edge across the plate (1 = none); colour: render a colour file; jpeg: JPEG
    quality (0 = none); defocus_px: extra Gaussian blur σ; texture_scale (× dot_px) and
    texture_contrast (DN, σ) of the background blotches; sheet_shade: factor on the sheet alone
    (a sheet in the shade before a sunlit garden); ink_gradient: each dot's contrast falls by
    this fraction across it along one direction (shading or uneven ink, as in real photographs: a
    dot darker on one side).
    """

    name: str
    width: int
    height: int
    dot_px: float
    focal_px: float = 0.0  # 0: 0.8 × the longer side
    tilt_deg: float = 0.0
    tilt_azimuth_deg: float = 30.0
    spin_deg: float = 0.0
    offset: tuple[float, float] = (0.0, 0.0)
    k1: float = 0.0
    k2: float = 0.0
    dark_dots: bool = True
    clutter: int = 0
    texture: bool = False
    shadow: float = 1.0
    colour: bool = False
    jpeg: int = 0
    defocus_px: float = 0.0
    gradient: float = 0.1
    vignetting: float = 0.1
    texture_scale: float = 3.0
    texture_contrast: float = 55.0
    sheet_shade: float = 1.0
    ink_gradient: float = 0.0
    seed: int = 0
    plate: DotPlate = field(default=ISSUE_PLATE)

    def camera(self) -> CameraModel:
        f_px = self.focal_px or 0.8 * max(self.width, self.height)
        pixel_mm = 0.002
        return CameraModel(self.width, self.height, pixel_mm, f_px * pixel_mm, (self.width - 1) / 2,
                           (self.height - 1) / 2, (self.k1, self.k2, 0.0, 0.0, 0.0), focus_distance_mm=1e6,
                           f_number=2.0, name=self.name)

    def pose(self) -> np.ndarray:
        """T_cam_plate (4, 4) mm: the plate at the distance that gives ``dot_px`` on the axis."""
        cam = self.camera()
        z = cam.fx_px * self.plate.dot_diameter_mm / self.dot_px
        x = self.offset[0] * (self.width / 2) * z / cam.fx_px
        y = self.offset[1] * (self.height / 2) * z / cam.fx_px
        az = math.radians(self.tilt_azimuth_deg)
        return facing_camera_pose([x, y, z], self.tilt_deg * math.cos(az), self.tilt_deg * math.sin(az),
                                  0.0, spin_deg=self.spin_deg)


def plate_outline_px(case: StressCase, n_per_side: int = 40) -> np.ndarray:
    """(4·n, 2) px: the sheet's outline through the camera (distortion included)."""
    plate = replace(case.plate, dark_dots=case.dark_dots)
    hx, hy = plate.half_extent_mm
    t = np.linspace(-1.0, 1.0, n_per_side, endpoint=False)
    sides = [np.stack([hx * t, -hy + 0 * t], 1), np.stack([hx + 0 * t, hy * t], 1),
             np.stack([-hx * t, hy + 0 * t], 1), np.stack([-hx + 0 * t, -hy * t], 1)]
    xy = np.concatenate(sides)
    pts = np.column_stack([xy, np.zeros(len(xy)), np.ones(len(xy))]) @ case.pose().T
    return project_points_ext(pts[:, :3], case.camera())


def smooth_noise(rng: np.random.Generator, shape: tuple[int, int], scale_px: float) -> np.ndarray:
    """Zero-mean, unit-σ smooth noise (H, W) float32 with features about ``scale_px`` across."""
    h, w = shape
    f = max(1, int(scale_px / 4))
    small = rng.standard_normal((h // f + 2, w // f + 2)).astype(np.float32)
    small = cv2.GaussianBlur(small, (0, 0), 2.0)
    out = cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
    return (out - out.mean()) / max(float(out.std()), 1e-6)


def _draw_clutter(img: np.ndarray, mask: np.ndarray, case: StressCase, rng: np.random.Generator) -> None:
    """Lines, text, boxes and blobs (half of them the dots' size) outside the sheet, in place."""
    h, w = img.shape
    layer = img.copy()
    d = case.dot_px
    for _ in range(case.clutter):
        kind = int(rng.integers(0, 4))
        level = float(rng.choice([20.0, 60.0, 230.0]))
        p0 = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        thick = max(1, int(rng.uniform(0.05, 0.3) * d))
        if kind == 0:
            p1 = (int(rng.integers(0, w)), int(rng.integers(0, h)))
            cv2.line(layer, p0, p1, level, thick, cv2.LINE_AA)
        elif kind == 1:
            text = "".join(rng.choice(list("ABCDEOQ0o8%@#"), size=int(rng.integers(2, 7))))
            cv2.putText(layer, text, p0, cv2.FONT_HERSHEY_SIMPLEX, float(rng.uniform(0.5, 2.0) * d / 20),
                        level, thick, cv2.LINE_AA)
        elif kind == 2:
            rad = max(2, int(rng.uniform(0.3, 1.3) * d / 2))
            cv2.circle(layer, p0, rad, level, -1, cv2.LINE_AA)
        else:
            p1 = (p0[0] + int(rng.uniform(0.5, 4) * d), p0[1] + int(rng.uniform(0.5, 4) * d))
            cv2.rectangle(layer, p0, p1, level, thick, cv2.LINE_AA)
    img[mask == 0] = layer[mask == 0]


def render_stress_case(case: StressCase) -> tuple[np.ndarray, np.ndarray]:
    """(image (H, W) uint8 grey, true dot centres (rows*cols, 2) px) of one stress case.

    The image is what a user's file would give after ``cv2.imread`` and ``COLOR_BGR2GRAY``.
    """
    rng = np.random.default_rng(case.seed)
    cam = case.camera()
    plate = replace(case.plate, dark_dots=case.dark_dots)
    pose = case.pose()
    cond = ImagingConditions(light_level=215.0, dark_level=35.0, background_level=90.0,
                             vignetting=case.vignetting, gradient=case.gradient, gradient_angle_deg=35.0,
                             defocus=False, aberration_sigma_px=0.6 + case.defocus_px)
    grey = render_plate_image(cam, plate, pose, cond, seed=case.seed).astype(np.float32)
    truth = true_dot_centres(cam, plate, pose)
    if case.ink_gradient:
        grey = _shade_dots(grey, truth, case, rng)
    mask = np.zeros(grey.shape, np.uint8)
    cv2.fillPoly(mask, [np.round(plate_outline_px(case) * 16).astype(np.int32)], 255, cv2.LINE_AA, shift=4)
    scale = max(case.width, case.height)
    if case.texture:  # blotchy background (foliage, a desk) and paper grain on the sheet
        blotch = smooth_noise(rng, grey.shape, case.texture_scale * case.dot_px)
        bg = np.clip(90.0 + case.texture_contrast * blotch, 0, 255)
        grain = 1.0 + 0.03 * smooth_noise(rng, grey.shape, max(2.0, scale / 400))
        grey = np.where(mask > 0, grey * grain * case.sheet_shade, bg + (grey - 90.0))
    img = np.clip(grey, 0, 255).astype(np.uint8)
    if case.clutter:
        _draw_clutter(img, mask, case, rng)
    out = img.astype(np.float32)
    if case.shadow < 1.0:  # a soft shadow edge (a hand, the phone) across the plate
        vv, uu = np.mgrid[0 : case.height, 0 : case.width].astype(np.float32)
        ang = rng.uniform(0, 2 * np.pi)
        c = np.array([case.width / 2, case.height / 2]) + rng.uniform(-0.1, 0.1, 2) * scale
        s = (uu - c[0]) * math.cos(ang) + (vv - c[1]) * math.sin(ang)
        soft = 1.0 / (1.0 + np.exp(-s / (0.02 * scale)))
        out *= case.shadow + (1.0 - case.shadow) * soft
    if case.defocus_px > 0:
        out = cv2.GaussianBlur(out, (0, 0), case.defocus_px)
    if case.colour:
        tint = np.array([0.82, 0.95, 1.0], np.float32)  # warm light on white paper (B, G, R)
        bgr = out[..., None] * tint + rng.normal(0.0, 3.0, (*out.shape, 3)).astype(np.float32)
        bgr = np.clip(np.rint(bgr), 0, 255).astype(np.uint8)
        if case.jpeg:
            bgr = cv2.imdecode(cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, case.jpeg])[1], cv2.IMREAD_COLOR)
        img = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    else:
        img = np.clip(np.rint(out), 0, 255).astype(np.uint8)
        if case.jpeg:
            img = cv2.imdecode(cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, case.jpeg])[1],
                               cv2.IMREAD_GRAYSCALE)
    return img, truth


def _shade_dots(grey: np.ndarray, centres: np.ndarray, case: StressCase, rng: np.random.Generator) -> np.ndarray:
    """``grey`` with each dot's contrast against the paper scaled by 1 − g·(1 − x/r)/2 along one
    random direction (x: offset from the nearest dot centre, clipped to ±r; r: dot radius; g:
    case.ink_gradient), out to 1.2 radii and fading to none at 1.4 (the paper around the dot,
    whose contrast is nil, is left alone): the dot's contrast falls linearly by the fraction g
    across it, the dot is darker on one side."""
    k = int(2 * case.dot_px) | 1
    extreme = cv2.dilate if case.dark_dots else cv2.erode
    paper = cv2.GaussianBlur(extreme(cv2.GaussianBlur(grey, (0, 0), 2.0), np.ones((k, k), np.uint8)), (0, 0),
                             case.dot_px / 2)
    vv, uu = np.mgrid[0 : grey.shape[0], 0 : grey.shape[1]].astype(np.float32)
    dist, nearest = cKDTree(centres).query(np.stack([uu.ravel(), vv.ravel()], axis=1))
    dist, nearest = dist.reshape(grey.shape), nearest.reshape(grey.shape)
    ang = rng.uniform(0, 2 * np.pi)
    r = case.dot_px / 2
    x = (uu - centres[nearest, 0]) * math.cos(ang) + (vv - centres[nearest, 1]) * math.sin(ang)
    near = np.clip((1.4 * r - dist) / (0.2 * r), 0.0, 1.0)
    gain = 1.0 - case.ink_gradient * (1.0 - np.clip(x / r, -1.0, 1.0)) / 2 * near  # ≤ 1: nothing clips
    return paper + (grey - paper) * gain


STRESS_CASES: tuple[StressCase, ...] = (
    StressCase("phone-12mp", 3024, 4032, 150.0, tilt_deg=10.0, spin_deg=3.0, clutter=40, texture=True,
               colour=True, jpeg=85, shadow=0.6, gradient=0.4, seed=1),
    StressCase("phone-12mp-light", 3024, 4032, 150.0, tilt_deg=20.0, spin_deg=-8.0, clutter=40, texture=True,
               colour=True, jpeg=85, dark_dots=False, seed=2),
    StressCase("phone-garden", 3024, 4032, 150.0, tilt_deg=8.0, spin_deg=-4.0, texture=True, texture_scale=0.3,
               texture_contrast=120.0, sheet_shade=0.55, jpeg=85, colour=True, seed=12),
    StressCase("phone-20px", 3024, 4032, 20.0, tilt_deg=25.0, spin_deg=10.0, clutter=60, texture=True,
               colour=True, jpeg=85, shadow=0.6, seed=11),
    StressCase("phone-400px", 3024, 4032, 400.0, tilt_deg=5.0, clutter=20, texture=True, colour=True, jpeg=85,
               seed=3),
    StressCase("fisheye", 320, 360, 30.0, focal_px=170.0, k1=-0.35, k2=0.1, offset=(0.15, 0.2), tilt_deg=25.0,
               clutter=15, texture=True, shadow=0.5, jpeg=90, colour=True, seed=4),
    StressCase("fisheye-light", 320, 360, 30.0, focal_px=170.0, k1=-0.35, k2=0.1, offset=(-0.2, 0.1),
               tilt_deg=20.0, clutter=15, dark_dots=False, jpeg=90, seed=5),
    StressCase("distant-15px", 640, 480, 15.0, tilt_deg=15.0, spin_deg=20.0, clutter=30, texture=True, jpeg=85,
               colour=True, seed=6),
    StressCase("distant-8px", 640, 480, 8.0, tilt_deg=10.0, clutter=20, jpeg=90, seed=7),
    StressCase("tilt-50", 1280, 960, 60.0, tilt_deg=50.0, tilt_azimuth_deg=10.0, spin_deg=35.0, clutter=20,
               texture=True, jpeg=85, seed=8),
    StressCase("uneven-light", 1280, 960, 40.0, tilt_deg=30.0, gradient=1.2, vignetting=0.5, shadow=0.35,
               clutter=20, jpeg=85, seed=9),
    StressCase("shaded-dots", 1280, 960, 32.0, tilt_deg=15.0, ink_gradient=0.6, defocus_px=1.5, clutter=10,
               jpeg=85, colour=True, seed=13),
    StressCase("light-tilt", 1280, 960, 50.0, tilt_deg=40.0, tilt_azimuth_deg=120.0, dark_dots=False,
               clutter=20, texture=True, colour=True, jpeg=85, seed=10),
    # off the fisheye's axis with the near side towards it, dots nearly touching (pitch 1.5 diameters):
    # the step from one row to the next grows by a third (a draw of random_fisheye_case)
    StressCase("fisheye-steps", 320, 360, 34.0, focal_px=170.0, k1=-0.35, k2=0.1, offset=(-0.19, 0.24),
               tilt_deg=20.0, tilt_azimuth_deg=34.0, spin_deg=-39.0, clutter=56, texture=True, colour=True, jpeg=90,
               seed=696575915),
    # light dots through the fisheye, clutter blobs of the dots' size one step beyond the grid (lattice-aligned
    # strays, not plate dots: a draw of random_fisheye_case)
    StressCase("fisheye-strays", 320, 360, 39.1, focal_px=170.0, k1=-0.35, k2=0.1, offset=(-0.316, 0.425),
               tilt_deg=31.1, tilt_azimuth_deg=296.1, spin_deg=-7.2, dark_dots=False, clutter=33, colour=True, jpeg=90,
               seed=1042573142),
    # the fisheye squeezes one side of the grid so hard that its rows turn by 45° from one dot to the next and
    # the dots shrink from 45 to 20 px (a draw of random_fisheye_case)
    StressCase("fisheye-squeezed", 320, 360, 36.7, focal_px=170.0, k1=-0.35, k2=0.1, offset=(0.232, 0.172),
               tilt_deg=32.0, tilt_azimuth_deg=296.2, spin_deg=-115.5, clutter=47, shadow=0.5, colour=True, jpeg=90,
               seed=93073361),
    # near the fisheye's axis the dots are 37 px, at its rim 18 px: no search band holds them all (a draw of
    # random_fisheye_case, seed 2)
    StressCase("fisheye-two-bands", 320, 360, 29.4, focal_px=170.0, k1=-0.35, k2=0.1, offset=(-0.430, -0.122),
               tilt_deg=33.5, tilt_azimuth_deg=81.9, spin_deg=67.2, clutter=52, texture=True, shadow=0.5, colour=True,
               jpeg=90, seed=55292379),
    # tilted away towards the fisheye's rim: the step from row to row shrinks by a third and more (51, 32, 21 px),
    # beyond a second difference's reach (a draw of random_fisheye_case, seed 2)
    StressCase("fisheye-shrinking", 320, 360, 37.0, focal_px=170.0, k1=-0.35, k2=0.1, offset=(-0.293, 0.268),
               tilt_deg=34.9, tilt_azimuth_deg=13.4, spin_deg=-27.7, clutter=38, colour=True, jpeg=90, seed=785639203),
    # an evenly lit page filling the frame: the 12 dots are under 1 % of the pixels, the grey range
    # is the paper's noise (as in real photographs of a small grid on a large sheet)
    StressCase("page-15px", 640, 480, 15.0, tilt_deg=10.0, spin_deg=5.0, jpeg=85, colour=True, gradient=0.0,
               vignetting=0.0, plate=replace(ISSUE_PLATE, margin_mm=400.0), seed=14),
    StressCase("page-12mp", 3024, 4032, 60.0, tilt_deg=5.0, jpeg=85, colour=True, gradient=0.0, vignetting=0.0,
               plate=replace(ISSUE_PLATE, margin_mm=400.0), seed=15),
)
"""The stress set: names say what each case stresses."""


def random_case(rng: np.random.Generator, name: str) -> StressCase | None:
    """A stress case drawn at random (image size, dot size 8 px … 1/6 of the image, tilt ≤ 50°,
    any spin, fisheye in 30 %, either polarity, clutter, texture, shadow, colour, JPEG 50–95,
    extra blur 0–2 px, uneven light), or None when its dots are not all wholly in the image."""
    w, h = [(640, 480), (320, 360), (1280, 960), (800, 600)][int(rng.integers(4))]
    big = max(w, h)
    fish = bool(rng.random() < 0.3)
    case = StressCase(
        name, w, h, float(np.exp(rng.uniform(np.log(8.0), np.log(big / 6.0)))), focal_px=0.55 * big if fish else 0.0,
        tilt_deg=float(rng.uniform(0, 50)), tilt_azimuth_deg=float(rng.uniform(0, 360)),
        spin_deg=float(rng.uniform(-180, 180)), offset=(float(rng.uniform(-0.3, 0.3)), float(rng.uniform(-0.3, 0.3))),
        k1=-0.35 if fish else float(rng.uniform(-0.1, 0.0)), k2=0.1 if fish else 0.0,
        dark_dots=bool(rng.random() < 0.7), clutter=int(rng.integers(0, 40)), texture=bool(rng.random() < 0.5),
        shadow=float(rng.choice([1.0, 0.6, 0.4])), colour=bool(rng.random() < 0.5),
        jpeg=int(rng.choice([0, 95, 85, 70, 50])), defocus_px=float(rng.choice([0.0, 0.0, 1.0, 2.0])),
        gradient=float(rng.uniform(0, 1)), vignetting=float(rng.uniform(0, 0.5)), seed=int(rng.integers(1 << 30)))
    plate = replace(case.plate, dark_dots=case.dark_dots)
    return case if plate_in_view(case.camera(), plate, case.pose(), border_px=1.0) else None


def random_fisheye_case(rng: np.random.Generator, name: str) -> StressCase | None:
    """A 320 × 360 frame through the fisheye stress case's lens (f 170 px, k1 −0.35, k2 0.1) drawn
    at random: dots of 20–40 px, the sheet up to 45 % of the half-frame off the axis, tilt ≤ 35°,
    any spin, 20–60 clutter items (half of them blobs), either polarity, shadow in half; or None
    when its dots are not all wholly in the image (the hidden fisheye regime of issue 33, with
    clutter added)."""
    case = StressCase(name, 320, 360, float(rng.uniform(20, 40)), focal_px=170.0, k1=-0.35, k2=0.1,
                      offset=(float(rng.uniform(-0.45, 0.45)), float(rng.uniform(-0.45, 0.45))),
                      tilt_deg=float(rng.uniform(0, 35)), tilt_azimuth_deg=float(rng.uniform(0, 360)),
                      spin_deg=float(rng.uniform(-180, 180)), clutter=int(rng.integers(20, 60)),
                      texture=bool(rng.random() < 0.5), shadow=float(rng.choice([1.0, 0.5])), jpeg=90, colour=True,
                      dark_dots=bool(rng.random() < 0.7), seed=int(rng.integers(1 << 30)))
    plate = replace(case.plate, dark_dots=case.dark_dots)
    return case if plate_in_view(case.camera(), plate, case.pose(), border_px=1.0) else None


def errors_up_to_symmetry(plate: DotPlate, centres: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Centre errors (rows*cols,) px under the flip of rows and/or columns that fits best: without
    a rotation prior a grid's orientation is a convention. centres, truth (rows*cols, 2) px."""
    g = centres.reshape(plate.rows, plate.cols, 2)
    best = None
    for flip_rows in (False, True):
        for flip_cols in (False, True):
            c = g[::-1] if flip_rows else g
            c = c[:, ::-1] if flip_cols else c
            e = np.linalg.norm(c.reshape(-1, 2) - truth, axis=1)
            if best is None or np.median(e) < np.median(best):
                best = e
    return best
