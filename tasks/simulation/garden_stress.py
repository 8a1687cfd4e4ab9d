"""Random photographs of a dot sheet on a clipboard held up in a garden, for the dot-grid detectors.

The hidden acceptance set of issue 33 photographs a printed 4 × 3 grid of dots on white paper on
a clipboard with a garden behind it, in three regimes: large phone photographs (3024 × 4032 JPEG,
nearly fronto-parallel, dots ≈ 150 px), a fisheye webcam (320 × 360, strong barrel distortion,
cast shadows) and small distant frames (640 × 480, dots ≈ 15 px). :func:`random_garden_case` draws
such a photograph at random in one regime, not modelled on any one image:

* the sheet (:func:`tasks.simulation.render.render_plate_image`, paper grain, a random margin
  round the dots) on a clipboard (a board of another colour beyond the sheet, a metal clip with
  a dark hole over the sheet's top edge, never over a dot);
* foliage around it: smooth leaf texture at several scales and many blobs of every size from a
  tenth of a dot to four dots, random ellipticity, angle and grey level (dark gaps and lit
  leaves, a share of them dark and round at the dots' own size), optionally out of focus;
* a cast shadow of a random shape across the scene, vignetting, exposure (the paper may
  saturate), defocus, the camera's sharpening (halos round every edge), a colour cast (green
  foliage, a brown board, warm paper), chroma noise, JPEG of quality 70–95, and the conversion to
  grey that ``fivecal detect`` applies (``cv2.COLOR_BGR2GRAY``).

Truth: :func:`tasks.simulation.render.true_dot_centres` (the projected 3-D dot centres, distortion
included). Frames: image px (u right, v down); plate mm as in :mod:`tasks.machine.plate`, origin
at the grid's centre.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from tasks.machine.distortion import undistort_pixels
from tasks.simulation.detector_stress import ISSUE_PLATE, StressCase, smooth_noise
from tasks.simulation.render import ImagingConditions, plate_in_view, render_plate_image, true_dot_centres

GARDEN_REGIMES = ("phone", "fisheye", "distant")
"""The hidden set's three regimes, as :func:`random_garden_case` draws them."""


@dataclass(frozen=True)
class GardenCase:
    """One garden photograph. ``geometry`` holds the camera, lens, pose, polarity and seed (its
    clutter, texture, shadow and colour fields are not used here); lengths in mm on the plate
    unless named _px, factors on the grey level.

    sheet_margin_mm: paper beyond the outermost dots' centres; board_margin_mm: clipboard beyond
    the sheet (three times that at the clip's side); clip: draw the clip; blob_density: foliage
    blobs per dot area of the image; foliage_blur_px: defocus σ of the garden; shadow: darkest
    factor of the cast shadow (1 = none); shadow_soft_px: σ of its edge; vignetting: fractional
    loss at the image corners; jpeg: quality; exposure: gain on the whole scene before the 8-bit
    clip (above 1 the paper saturates); blur_px: defocus σ of the whole image (a phone focused a
    little off the sheet); sharpen: amount of the camera's unsharp mask (radius ``sharpen_px``), whose
    halos ring every edge.
    """

    geometry: StressCase
    sheet_margin_mm: float = 10.0
    board_margin_mm: float = 8.0
    clip: bool = True
    blob_density: float = 1.5
    foliage_blur_px: float = 0.0
    shadow: float = 0.6
    shadow_soft_px: float = 10.0
    vignetting: float = 0.3
    jpeg: int = 85
    exposure: float = 1.0
    blur_px: float = 0.0
    sharpen: float = 0.0
    sharpen_px: float = 2.0

    @property
    def name(self) -> str:
        return self.geometry.name

    @property
    def plate(self):
        """The sheet: the issue's plate with this case's polarity and margin."""
        return replace(ISSUE_PLATE, dark_dots=self.geometry.dark_dots, margin_mm=self.sheet_margin_mm)


def random_garden_case(rng: np.random.Generator, name: str, regime: str = "phone") -> GardenCase | None:
    """A garden photograph of the sheet drawn at random in ``regime`` (:data:`GARDEN_REGIMES`), or None
    when its dots are not all wholly in the image.

    phone: 3024 × 4032, dots 80–250 px, tilt ≤ 15°, the sheet turned by a multiple of 90° ± 10°, a
    phone lens (k1 −0.05…+0.02). fisheye: 320 × 360 through the fisheye stress case's lens (f 170 px,
    k1 −0.35, k2 0.1), dots 18–40 px, tilt ≤ 35°, up to 45 % of the half-frame off the axis, any
    spin, always a cast shadow. distant: 640 × 480, dots 10–20 px, tilt ≤ 30°, any spin. Dark dots
    in 80 %."""
    if regime not in GARDEN_REGIMES:
        raise ValueError(f"unknown garden regime {regime!r}; expected one of {GARDEN_REGIMES}")
    u = rng.uniform
    if regime == "phone":
        w, h, dot = 3024, 4032, float(np.exp(u(np.log(80.0), np.log(250.0))))
        tilt, spin = u(0, 15), 90.0 * int(rng.integers(4)) + u(-10, 10)
        off, k1, k2, focal = (u(-0.2, 0.2), u(-0.2, 0.2)), u(-0.05, 0.02), 0.0, 0.0
    elif regime == "fisheye":
        w, h, dot = 320, 360, u(18, 40)
        tilt, spin = u(0, 35), u(-180, 180)
        off, k1, k2, focal = (u(-0.45, 0.45), u(-0.45, 0.45)), -0.35, 0.1, 170.0
    else:
        w, h, dot = 640, 480, u(10, 20)
        tilt, spin = u(0, 30), u(-180, 180)
        off, k1, k2, focal = (u(-0.3, 0.3), u(-0.3, 0.3)), u(-0.1, 0.0), 0.0, 0.0
    geometry = StressCase(name, w, h, dot, focal_px=focal, tilt_deg=tilt, tilt_azimuth_deg=u(0, 360), spin_deg=spin,
                          offset=off, k1=k1, k2=k2, dark_dots=bool(rng.random() < 0.8),
                          seed=int(rng.integers(1 << 30)))
    case = GardenCase(geometry, sheet_margin_mm=u(3.0, 30.0), board_margin_mm=u(3.0, 20.0),
                      clip=bool(rng.random() < 0.8),
                      blob_density=u(0.5, 3.0), foliage_blur_px=float(rng.choice([0.0, 0.0, u(0.02, 0.15) * dot])),
                      shadow=1.0 if (regime != "fisheye" and rng.random() < 0.3) else u(0.35, 0.8),
                      shadow_soft_px=u(0.05, 1.0) * dot, vignetting=u(0.0, 0.5), jpeg=int(rng.integers(70, 96)),
                      exposure=u(0.8, 1.3), blur_px=u(0.0, 0.02) * dot, sharpen=float(rng.choice([0.0, u(0.3, 1.5)])),
                      sharpen_px=u(1.0, 3.0))
    dots = replace(ISSUE_PLATE, dark_dots=geometry.dark_dots)
    return case if plate_in_view(geometry.camera(), dots, geometry.pose(), border_px=1.0) else None


def plate_coordinates(case: GardenCase, step_px: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """(X, Y) (H, W) float32 mm: where each pixel's ray meets the plate's plane, in plate coordinates
    (NaN where it misses), computed every ``step_px`` pixels through the exact inverse of the lens
    model (as the renderer maps pixels, so outlines drawn with it agree with the rendered sheet even
    where a fisheye's model folds) and interpolated linearly in between."""
    g = case.geometry
    cam, T = g.camera(), g.pose()
    us = np.arange(0, g.width + step_px, step_px, dtype=float)
    vs = np.arange(0, g.height + step_px, step_px, dtype=float)
    uv = np.stack(np.meshgrid(us, vs), axis=-1)
    xy = undistort_pixels(uv, cam)
    hom = np.linalg.inv(np.column_stack([T[:3, 0], T[:3, 1], T[:3, 3]]))  # normalised image → plate (X, Y, 1)
    p = np.concatenate([xy, np.ones((*xy.shape[:2], 1))], axis=-1) @ hom.T
    w = np.where(p[..., 2] > 0, p[..., 2], np.nan)
    coarse = (p[..., :2] / w[..., None]).astype(np.float32)
    # pixel u lies at coarse index u / step_px: scale the coarse map so that its node k lands on pixel k·step
    mx, my = np.meshgrid(np.arange(g.width, dtype=np.float32) / step_px,
                         np.arange(g.height, dtype=np.float32) / step_px)
    out = [cv2.remap(coarse[..., i], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE) for i in (0, 1)]
    return out[0], out[1]


def _rectangle(xy: tuple[np.ndarray, np.ndarray], x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
    """(H, W) float32 coverage 0…1 of the plate-frame rectangle [x0, x1] × [y0, y1] mm, from the
    pixels' plate coordinates ``xy`` (:func:`plate_coordinates`), its edge softened over a pixel."""
    x, y = xy
    inside = ((x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)).astype(np.float32)
    return cv2.GaussianBlur(inside, (0, 0), 0.5)


def foliage(rng: np.random.Generator, shape: tuple[int, int], dot_px: float, density: float) -> np.ndarray:
    """(H, W) float32 grey of a garden: leaf texture at three scales and ``density`` × (image area /
    dot area) elliptical blobs of 0.1–4 dot diameters (a quarter dark, round and of the dots' own
    size), random grey level, ellipticity and angle."""
    h, w = shape
    img = 90.0 + 35.0 * smooth_noise(rng, shape, 3.0 * dot_px) + 20.0 * smooth_noise(rng, shape, 0.6 * dot_px)
    n = int(min(4000, density * h * w / dot_px**2))
    for _ in range(n):
        if rng.random() < 0.25:  # a dark gap between leaves the size of a dot
            d, ratio, level = dot_px * rng.uniform(0.7, 1.4), rng.uniform(0.6, 1.0), rng.uniform(5, 60)
        else:
            d = dot_px * float(np.exp(rng.uniform(np.log(0.1), np.log(4.0))))
            ratio, level = rng.uniform(0.25, 1.0), float(rng.choice([rng.uniform(5, 60), rng.uniform(60, 150),
                                                                       rng.uniform(150, 250)]))
        centre = (int(rng.uniform(0, w) * 16), int(rng.uniform(0, h) * 16))
        axes = (max(1, int(d * 8)), max(1, int(d * ratio * 8)))
        cv2.ellipse(img, centre, axes, float(rng.uniform(0, 180)), 0, 360, float(level), -1, cv2.LINE_AA, shift=4)
    img += 12.0 * smooth_noise(rng, shape, max(2.0, 0.08 * dot_px))  # veins, grain of the leaves
    return img


def _cast_shadow(rng: np.random.Generator, shape: tuple[int, int], centre_px: np.ndarray, size_px: float,
                 darkest: float, soft_px: float) -> np.ndarray:
    """(H, W) float32 light factor of a cast shadow (a hand, a branch): a random smooth blob about
    ``size_px`` across, centred off ``centre_px`` by up to half its size, ``darkest`` inside, its
    edge blurred by ``soft_px``."""
    k = 9
    ang = np.sort(rng.uniform(0, 2 * np.pi, k))
    rad = size_px / 2 * rng.uniform(0.5, 1.2, k)
    c = centre_px + rng.uniform(-0.5, 0.5, 2) * size_px
    poly = np.column_stack([c[0] + rad * np.cos(ang), c[1] + rad * np.sin(ang)])
    inside = np.zeros(shape, np.uint8)
    cv2.fillPoly(inside, [np.round(poly * 16).astype(np.int32)], 255, cv2.LINE_AA, shift=4)
    cover = inside.astype(np.float32) / 255.0
    if soft_px > 40.0:  # a wide blur on a 12 MP frame: at a tenth of the resolution (the edge is smooth)
        small = cv2.resize(cover, (max(1, shape[1] // 10), max(1, shape[0] // 10)), interpolation=cv2.INTER_AREA)
        cover = cv2.resize(cv2.GaussianBlur(small, (0, 0), soft_px / 10), (shape[1], shape[0]),
                           interpolation=cv2.INTER_LINEAR)
    elif soft_px > 0.3:
        cover = cv2.GaussianBlur(cover, (0, 0), soft_px)
    return 1.0 - (1.0 - darkest) * cover


def render_garden_case(case: GardenCase) -> tuple[np.ndarray, np.ndarray]:
    """(image (H, W) uint8 grey, true dot centres (rows*cols, 2) px) of one garden photograph:
    what ``cv2.imread`` and ``COLOR_BGR2GRAY`` give from the JPEG file."""
    g = case.geometry
    rng = np.random.default_rng(g.seed)
    cam, pose, sheet = g.camera(), g.pose(), case.plate
    shape = (g.height, g.width)
    cond = ImagingConditions(light_level=220.0, dark_level=30.0, background_level=90.0, vignetting=0.0,
                             gradient=float(rng.uniform(0, 0.3)), gradient_angle_deg=float(rng.uniform(0, 360)),
                             defocus=False, aberration_sigma_px=0.6)
    paper = render_plate_image(cam, sheet, pose, cond, seed=g.seed).astype(np.float32)
    paper *= 1.0 + 0.03 * smooth_noise(rng, shape, max(2.0, max(shape) / 400))
    truth = true_dot_centres(cam, sheet, pose)
    hx, hy = sheet.half_extent_mm
    b = case.board_margin_mm
    top = -1.0 if rng.random() < 0.5 else 1.0  # the clip's side of the board (plate −y or +y)
    y0, y1 = (-hy - 3 * b, hy + b) if top < 0 else (-hy - b, hy + 3 * b)
    xy = plate_coordinates(case)
    on_sheet = _rectangle(xy, -hx, hx, -hy, hy)
    on_board = _rectangle(xy, -hx - b, hx + b, y0, y1)
    board_grey = float(rng.uniform(60, 170))
    board = board_grey * (1.0 + 0.08 * smooth_noise(rng, shape, max(2.0, 0.3 * g.dot_px)))
    garden = foliage(rng, shape, g.dot_px, case.blob_density)
    if case.foliage_blur_px > 0.3:
        garden = cv2.GaussianBlur(garden, (0, 0), case.foliage_blur_px)
    grey = garden * (1 - on_board) + board * (on_board - on_sheet) + paper * on_sheet
    on_clip = np.zeros(shape, np.float32)
    if case.clip:  # over the sheet's edge at the top, stopping 2 mm short of the dots' rims
        dots_edge = float(np.abs(sheet.dot_centres_mm()[:, 1]).max()) + sheet.dot_diameter_mm / 2 + 2.0
        cw = rng.uniform(0.25, 0.45) * (hx + b)
        reach = min(hy, dots_edge + rng.uniform(0.0, max(hy - dots_edge, 0.0)))
        ya, yb = sorted((top * (hy + 2.5 * b), top * reach))
        on_clip = _rectangle(xy, -cw, cw, ya, yb)
        metal = float(rng.uniform(110, 210)) * (1.0 + 0.1 * smooth_noise(rng, shape, 0.5 * g.dot_px))
        grey = grey * (1 - on_clip) + metal * on_clip
        hole_cover = _rectangle(xy, -0.15 * cw, 0.15 * cw, (ya + yb) / 2 - 0.15 * cw, (ya + yb) / 2 + 0.15 * cw)
        grey = grey * (1 - hole_cover) + 25.0 * hole_cover
    if case.shadow < 1.0:
        size = float(np.ptp(truth, axis=0).max()) * rng.uniform(0.8, 2.5)
        grey *= _cast_shadow(rng, shape, truth.mean(axis=0), size, case.shadow, case.shadow_soft_px)
    vv, uu = np.mgrid[0 : g.height, 0 : g.width].astype(np.float32)
    r2 = ((uu - g.width / 2) ** 2 + (vv - g.height / 2) ** 2) / ((g.width / 2) ** 2 + (g.height / 2) ** 2)
    grey *= case.exposure * (1.0 - case.vignetting * r2)
    if case.blur_px > 0.3:
        grey = cv2.GaussianBlur(grey, (0, 0), case.blur_px)
    if case.sharpen > 0:  # the phone's unsharp mask: a halo on either side of every edge
        grey = grey + case.sharpen * (grey - cv2.GaussianBlur(grey, (0, 0), case.sharpen_px))
    bgr = _colour(rng, grey, 1 - on_board, np.clip(on_board - on_sheet, 0, 1) * (1 - on_clip),
                  np.clip(on_sheet + on_clip, 0, 1))
    bgr = cv2.imdecode(cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, case.jpeg])[1], cv2.IMREAD_COLOR)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), truth


def _colour(rng: np.random.Generator, grey: np.ndarray, garden: np.ndarray, board: np.ndarray, sheet: np.ndarray
            ) -> np.ndarray:
    """(H, W, 3) uint8 BGR: ``grey`` tinted per region (coverages (H, W)): green foliage varying in
    hue, a brown board, warm or cool paper (and the clip, with it in ``sheet``); chroma noise of 3 DN.
    The tints keep the region's luma (BGR2GRAY weights), so the grey image stays what the scene's greys say."""
    luma = np.array([0.114, 0.587, 0.299], np.float32)

    def tint(bgr) -> np.ndarray:
        t = np.asarray(bgr, np.float32)
        return t / float(t @ luma)

    leaf = tint([rng.uniform(0.2, 0.5), 1.0, rng.uniform(0.4, 0.8)])
    leaf2 = tint([rng.uniform(0.3, 0.6), 0.9, rng.uniform(0.7, 1.0)])  # yellowed, sunlit
    mix = np.clip(0.5 + 0.5 * smooth_noise(rng, grey.shape, max(grey.shape) / 10), 0, 1)[..., None]
    wood = tint([rng.uniform(0.3, 0.6), rng.uniform(0.6, 0.8), 1.0])
    paper = tint([rng.uniform(0.8, 1.0), rng.uniform(0.92, 1.0), rng.uniform(0.9, 1.0)])
    t = (garden[..., None] * (mix * leaf + (1 - mix) * leaf2) + board[..., None] * wood
         + sheet[..., None] * paper)
    bgr = grey[..., None] * t + rng.normal(0.0, 3.0, (*grey.shape, 3)).astype(np.float32)
    return np.clip(np.rint(bgr), 0, 255).astype(np.uint8)


