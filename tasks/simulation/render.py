"""Simulated camera images of a dot calibration plate.

The renderer traces, for every pixel centre that lies near an edge, the (undistorted) ray back
to the plate plane and integrates the optically blurred dot / plate edge over the pixel, so that
a noiseless, in-focus dot rendered near-frontally has its intensity centroid at the projection
of its 3D centre (the only remaining bias being the true optics: perspective and distortion of
the dot's finite size).

Frames and units
----------------
* Plate frame (mm): as in :mod:`tasks.machine.plate` (origin at the grid centre, +X along columns,
  +Y along rows, +Z out of the printed face).
* Camera frame (mm): OpenCV convention, +Z along the optical axis, +X towards increasing u,
  +Y towards increasing v.  ``T_cam_plate`` is the 4×4 homogeneous transform taking plate-frame
  points to camera-frame points: ``p_cam = T_cam_plate @ [X, Y, Z, 1]``.
* Pixels: (u, v) with the origin at the centre of the top-left pixel; pixel (row i, col j)
  covers u ∈ [j − ½, j + ½], v ∈ [i − ½, i + ½].
* Grey levels: 0–255 (DN), floating point until the final 8-bit quantisation.

Pipeline of :func:`render_plate_image`
--------------------------------------
1. Exact inverse distortion on a coarse node grid (every ``TILE_PX`` px, vectorised Newton),
   Catmull–Rom interpolation in between (≤ 0.002 px, see ``tests/simulation/test_render.py``).
2. The image is cut into ``TILE_PX``×``TILE_PX`` tiles.  Tiles that are provably uniform
   (inside a dot, on bare plate, or off the plate) get one value; only tiles within reach of a
   dot edge or a plate edge are rendered per pixel: ray → plate point → signed distance to the
   edge (mm) → pixels via the local Jacobian → the pixel-square integral of the edge blurred by
   a Gaussian of σ ≤ ``ANALYTIC_BLUR_MAX_PX`` (closed form; σ = 0 is the exact area coverage).
3. Optical blur: Gaussian with σ² = aberration² + diffraction² + (CoC/2.355)², CoC from the
   thin-lens model at the depth of the plate point seen by each pixel.  Up to
   ``ANALYTIC_BLUR_MAX_PX`` it is already in the edges (step 2); the rest is a sampled Gaussian
   (spatially varying: a few σ levels blended).
4. Gain: cos⁴-like vignetting × linear illumination gradient.
5. Noise: Gaussian with variance read² + level/gain (read noise + Gaussian approximation of
   shot noise; deviates by 16-bit inverse-CDF lookup), then rounding and clipping to uint8.

Gain is applied after the blur: it varies slowly, so the order changes nothing measurable.
Plates seen from behind render blank (no dots); exactly edge-on, not at all.

No Prefect import here: numpy, SciPy (the normal CDF) and OpenCV only.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from scipy.special import ndtr

from tasks.machine.camera_model import CameraModel
from tasks.machine.distortion import TILE_PX, ExtraDistortion, project_points_ext, undistortion_grid
from tasks.machine.plate import DotPlate

"""Tile edge and coarse undistortion-grid spacing (px)."""

_BLUR_STRIP_TILES = 8

MAX_BLUR_SIGMA_PX = 50.0
"""Blur σ is capped here (px): only reached for a plate almost touching the lens."""

ANALYTIC_BLUR_MAX_PX = 1.5
"""Blur up to this σ (px) is rendered into each edge pixel analytically, as the pixel integral of
the blurred edge (:func:`_blurred_edge_coverage`); only the rest, √(σ² − 1.5²), is a sampled
Gaussian over the image.  Box coverages blurred by a sampled kernel of σ ≲ 1 px have a shape
that changes with the edge's sub-pixel phase, which a detector reads as a shift that locks to
the pixel grid; past 1.5 px a sampled kernel on an already smooth image is exact enough."""

FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))  # 2.3548...


# --------------------------------------------------------------------------------------------
# Imaging conditions
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ImagingConditions:
    """Photometric and optical conditions of one exposure.

    Levels are grey levels (DN, 0–255) at the image centre, before gain maps and noise.

    light_level: the light material: the plate face for dark-dot plates, the dots for
        light-dot plates (``DotPlate.dark_dots`` decides which is which).
    dark_level: the dark material (dots of a dark-dot plate, face of a light-dot plate).
    background_level: seen outside the plate (only when ``plate.margin_mm > 0``; a plate with
        no margin is treated as infinite).
    vignetting: fractional loss of light at the image corner farthest from the principal point
        (0 = none, 0.2 = the corner gets 80 %).  Profile ``g(r) = (1 + a r²)⁻²`` (cos⁴ law of a
        lens whose effective focal length is chosen so that g(r_corner) = 1 − vignetting),
        r measured from (cx, cy) in px.
    gradient: total fractional change of illumination across the image along
        ``gradient_angle_deg`` (0.1 = the bright side gets +5 %, the dark side −5 %, relative to
        the image centre).  Linear.
    gradient_angle_deg: direction of increasing light, degrees from +u towards +v.
    read_noise_dn: read-noise standard deviation (DN).
    shot_noise_gain_e_per_dn: electrons per DN.  Shot noise variance = level / gain (DN²);
        ``None`` or ≤ 0 disables shot noise.  Drawn as Gaussian (Poisson is Gaussian at these
        counts): one standard normal per pixel from :func:`standard_normal_image`.
    aberration_sigma_px: Gaussian σ (px) of the lens aberrations at focus.
    diffraction: add the diffraction blur of the aperture, :func:`diffraction_sigma_px` at
        ``wavelength_um``.
    wavelength_um: wavelength of the (narrow-band) illumination (µm).
    defocus: apply thin-lens defocus blur from ``CameraModel.focus_distance_mm``, ``f_number``
        and ``focal_length_mm``.  The circle of confusion diameter c (px) is turned into a
        Gaussian σ = c · ``coc_sigma_per_diameter`` (default 1/2.355: FWHM = c).

    Vignetting and the gradient are physical and do move intensity centroids: a dot of
    variance s² (px²) on a gain slope ∇g/g shifts by ≈ s²·∇g/g (up to ~0.08 px for plate "a"
    near the image edge with vignetting 0.15), unless the detector normalises by the local
    plate level.  Use :meth:`ideal` for bias-free references.
    """

    light_level: float = 200.0
    dark_level: float = 30.0
    background_level: float = 15.0
    vignetting: float = 0.15
    gradient: float = 0.05
    gradient_angle_deg: float = 0.0
    read_noise_dn: float = 1.5
    shot_noise_gain_e_per_dn: float | None = 20.0
    aberration_sigma_px: float = 0.6
    diffraction: bool = True
    wavelength_um: float = 0.55
    defocus: bool = True
    coc_sigma_per_diameter: float = 1.0 / FWHM_PER_SIGMA

    @classmethod
    def ideal(cls, **overrides) -> ImagingConditions:
        """No vignetting, no gradient, no noise; the optical blur kept (override freely)."""
        kw: dict = {
            "vignetting": 0.0,
            "gradient": 0.0,
            "read_noise_dn": 0.0,
            "shot_noise_gain_e_per_dn": None,
        }
        kw.update(overrides)
        return cls(**kw)

    def plate_and_dot_levels(self, plate: DotPlate) -> tuple[float, float]:
        """(plate face level, dot level) in DN for this plate's polarity."""
        if plate.dark_dots:
            return self.light_level, self.dark_level
        return self.dark_level, self.light_level


# --------------------------------------------------------------------------------------------
# Geometry helpers
# --------------------------------------------------------------------------------------------


def _check_pose(T_cam_plate) -> np.ndarray:
    T = np.asarray(T_cam_plate, dtype=float)
    if T.shape != (4, 4):
        raise ValueError(f"T_cam_plate must be 4x4, got {T.shape}")
    return T


def _plate_to_cam(points_plate_mm: np.ndarray, T: np.ndarray) -> np.ndarray:
    return points_plate_mm @ T[:3, :3].T + T[:3, 3]


def true_dot_centres(
    camera: CameraModel,
    plate: DotPlate,
    T_cam_plate: np.ndarray,
    extra_distortion: ExtraDistortion | Sequence[float] | None = None,
) -> np.ndarray:
    """(rows*cols, 2) pixel projections (u, v) of the 3D dot centres, row-major like
    ``DotPlate.dot_centres_mm``.  Note: this is the projected centre, not the centroid of the
    projected dot (they differ by perspective/distortion bias of order f·(R/Z)²·tan(tilt))."""
    T = _check_pose(T_cam_plate)
    return project_points_ext(_plate_to_cam(plate.dot_centres_mm(), T), camera, extra_distortion)


def plate_faces_camera(T_cam_plate: np.ndarray) -> bool:
    """True if the camera centre is on the printed (+Z_plate) side of the plate plane."""
    T = _check_pose(T_cam_plate)
    # cosine of the viewing angle must exceed 1e-9 (exactly edge-on counts as not facing)
    return float(np.dot(T[:3, 2], T[:3, 3])) < -1e-9 * float(np.linalg.norm(T[:3, 3]))


def plate_in_view(
    camera: CameraModel,
    plate: DotPlate,
    T_cam_plate: np.ndarray,
    extra_distortion: ExtraDistortion | Sequence[float] | None = None,
    *,
    border_px: float = 0.0,
    n_rim: int = 32,
) -> bool:
    """True if every dot, rim included, projects inside the image (at least ``border_px`` px from
    the outer pixel edges), lies in front of the camera, and the printed face (+Z_plate) faces
    the camera (a plate seen from behind or edge-on shows no dots).  The rim is sampled at
    ``n_rim`` points per dot."""
    T = _check_pose(T_cam_plate)
    if not plate_faces_camera(T):
        return False
    R = plate.dot_diameter_mm / 2.0
    a = np.linspace(0.0, 2.0 * np.pi, n_rim, endpoint=False)
    rim = np.stack([R * np.cos(a), R * np.sin(a), np.zeros_like(a)], -1)
    pts = (plate.dot_centres_mm()[:, None, :] + rim[None]).reshape(-1, 3)
    pc = _plate_to_cam(pts, T)
    if np.any(pc[:, 2] <= 0.0):
        return False
    uv = project_points_ext(pc, camera, extra_distortion)
    lo = -0.5 + border_px
    return bool(
        np.all(uv[:, 0] >= lo)
        and np.all(uv[:, 1] >= lo)
        and np.all(uv[:, 0] <= camera.width_px - 0.5 - border_px)
        and np.all(uv[:, 1] <= camera.height_px - 0.5 - border_px)
    )


def circle_of_confusion_px(camera: CameraModel, depth_mm: np.ndarray | float) -> np.ndarray:
    """Thin-lens blur-circle diameter (px) for object depth Z (mm, along +Z).

    c = A · f / (s_f − f) · |Z − s_f| / Z,  A = f / N (aperture diameter),
    f = focal_length_mm, s_f = focus_distance_mm, N = f_number; divided by pixel_size_mm.
    """
    f = camera.focal_length_mm
    sf = camera.focus_distance_mm
    A = f / camera.f_number
    z = np.asarray(depth_mm, dtype=float)
    return A * f / (sf - f) * np.abs(z - sf) / z / camera.pixel_size_mm


def diffraction_sigma_px(camera: CameraModel, wavelength_um: float) -> float:
    """σ (px) of the Gaussian that best fits the in-focus Airy pattern of the camera's aperture.

    σ = 0.42 λ N_w (Zhang, Zerubia & Olivo-Marin 2007), with the working f-number
    N_w = N · s_f / (s_f − f) of a lens focused at s_f (the image lies behind the focal plane);
    λ in µm, divided by the pixel pitch.  The 16 mm f/8 lens with 2.4 µm pixels gives 0.81 px
    focused at 300 mm, 0.96 px at 80 mm.
    """
    f = camera.focal_length_mm
    sf = camera.focus_distance_mm
    n_working = camera.f_number * sf / (sf - f)
    return 0.42 * wavelength_um * 1e-3 * n_working / camera.pixel_size_mm


def blur_sigma_px(camera: CameraModel, conditions: ImagingConditions, depth_mm) -> np.ndarray:
    """Total Gaussian σ (px) at object depth Z (mm): √(aberration² + diffraction² + defocus²),
    defocus σ = CoC · ``coc_sigma_per_diameter``."""
    s0 = conditions.aberration_sigma_px**2
    if conditions.diffraction:
        s0 += diffraction_sigma_px(camera, conditions.wavelength_um) ** 2
    s2 = np.full(np.shape(depth_mm), s0)
    if conditions.defocus:
        s2 = s2 + (circle_of_confusion_px(camera, depth_mm) * conditions.coc_sigma_per_diameter) ** 2
    return np.sqrt(s2)


def _blurred_edge_coverage(t_in: np.ndarray, gu: np.ndarray, gv: np.ndarray, sigma_px) -> np.ndarray:
    """Pixel average of a Gaussian-blurred straight edge: what a sensor pixel records (float32).

    t_in: signed distance (px) from the pixel centre to the edge, positive inside.
    gu, gv: components of the edge normal in pixel axes (any length; only |gu|:|gv| matters).
    sigma_px: Gaussian blur σ (px) of the optics, scalar or per pixel; 0 gives the exact area
        coverage of the pixel square (the box filter of a half-plane).
    Returns E[Φ((t_in + p·U₁ + q·U₂)/σ)] with U uniform on (−½, ½) and (p, q) the components of
    the unit normal: the pixel-box integral of the blurred edge, from second antiderivatives of
    Φ (closed form, float64).  Rendering it directly, instead of blurring box coverages with a
    sampled kernel, keeps the edge's shape independent of its sub-pixel phase.
    """
    t = np.asarray(t_in, dtype=np.float64)
    ax = np.abs(np.broadcast_to(np.asarray(gu, dtype=np.float64), t.shape))
    ay = np.abs(np.broadcast_to(np.asarray(gv, dtype=np.float64), t.shape))
    s = np.maximum(np.broadcast_to(np.asarray(sigma_px, dtype=np.float64), t.shape), 1e-9)
    # only the transition band needs the closed form: beyond ½(p + q) + 6σ it is 0 or 1 (< 1e-9)
    out = (t > 0).astype(np.float32)
    band = np.abs(t) < 0.75 + 6.0 * s  # ½(p + q) ≤ 1/√2
    t, ax, ay, s = t[band], ax[band], ay[band], s[band]
    norm = np.maximum(np.hypot(ax, ay), 1e-30)
    p = np.maximum(np.maximum(ax, ay) / norm, math.sqrt(0.5))  # larger component; guards g = 0
    q = np.minimum(ax, ay) / norm
    inv_sqrt_2pi = 1.0 / math.sqrt(2.0 * math.pi)

    def first(x, s):  # ∫ Φ(x/σ) dx
        z = x / s
        return x * ndtr(z) + s * inv_sqrt_2pi * np.exp(-0.5 * z * z)

    def second(x, s):  # ∫∫ Φ(x/σ) dx dx
        z = x / s
        return 0.5 * ((x * x + s * s) * ndtr(z) + x * s * inv_sqrt_2pi * np.exp(-0.5 * z * z))

    value = np.empty_like(t)
    thin = q < 1e-3  # the 1-D formula: the 2-D one cancels catastrophically as q → 0
    k = np.nonzero(thin)[0]
    if k.size:
        tk, pk, sk = t[k], p[k], s[k]
        value[k] = (first(tk + pk / 2, sk) - first(tk - pk / 2, sk)) / pk
    k = np.nonzero(~thin)[0]
    if k.size:
        tk, pk, qk, sk = t[k], p[k], q[k], s[k]
        value[k] = (second(tk + (pk + qk) / 2, sk) - second(tk + (pk - qk) / 2, sk)
                    - second(tk - (pk - qk) / 2, sk) + second(tk - (pk + qk) / 2, sk)) / (pk * qk)
    out[band] = np.clip(value, 0.0, 1.0)
    return out


# --------------------------------------------------------------------------------------------
# Gain map (vignetting × illumination gradient)
# --------------------------------------------------------------------------------------------


@lru_cache(maxsize=4)
def _gain_map_cached(w: int, h: int, cx: float, cy: float, vig: float, grad: float, ang: float) -> np.ndarray:
    u = np.arange(w, dtype=np.float64) - cx
    v = np.arange(h, dtype=np.float64) - cy
    g = np.ones((h, w), np.float32)
    if vig != 0.0:
        rc2 = max((-0.5 - cx) ** 2, (w - 0.5 - cx) ** 2) + max((-0.5 - cy) ** 2, (h - 0.5 - cy) ** 2)
        a = (1.0 / math.sqrt(1.0 - vig) - 1.0) / rc2
        q = (1.0 + a * u * u).astype(np.float32)[None, :] + (a * v * v).astype(np.float32)[:, None]
        q *= q
        np.divide(np.float32(1.0), q, out=g)
    if grad != 0.0:
        c, s = math.cos(math.radians(ang)), math.sin(math.radians(ang))
        span = (w - 1) * abs(c) + (h - 1) * abs(s)
        # linear about the image centre, ±grad/2 at the extreme corners along the direction
        uc, vc = (w - 1) / 2.0, (h - 1) / 2.0
        lu = (grad * c / span * (np.arange(w) - uc)).astype(np.float32)
        lv = (grad * s / span * (np.arange(h) - vc)).astype(np.float32)
        g *= np.float32(1.0) + lu[None, :] + lv[:, None]
    g.setflags(write=False)
    return g


def gain_map(camera: CameraModel, conditions: ImagingConditions) -> np.ndarray:
    """(H, W) float32 multiplicative gain: vignetting × illumination gradient (1 at the centre
    when there is no gradient).  Read-only, cached by exact parameters."""
    return _gain_map_cached(
        camera.width_px,
        camera.height_px,
        float(camera.cx_px),
        float(camera.cy_px),
        float(conditions.vignetting),
        float(conditions.gradient),
        float(conditions.gradient_angle_deg),
    )


# --------------------------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------------------------


def _tile_view(img: np.ndarray, T: int) -> np.ndarray:
    """(nty, ntx, T, T) writable view of a (nty*T, ntx*T) array."""
    h, w = img.shape
    return img.reshape(h // T, T, w // T, T).swapaxes(1, 2)


def _nearest_dot_distance(X, Y, plate: DotPlate):
    """Distance (mm) and unit direction from the nearest dot centre to plate point (X, Y)."""
    px, py = plate.pitch_mm, plate.pitch_y_mm
    oc = (plate.cols - 1) / 2.0
    orow = (plate.rows - 1) / 2.0
    c = np.clip(np.rint(X / px + oc), 0, plate.cols - 1)
    r = np.clip(np.rint(Y / py + orow), 0, plate.rows - 1)
    dx = X - (c - oc) * px
    dy = Y - (r - orow) * py
    return dx, dy, np.hypot(dx, dy)


def _box_signed_distance(X, Y, hx: float, hy: float):
    """Signed distance (mm, positive outside) to the rectangle |X| ≤ hx, |Y| ≤ hy, and a
    (non-normalised) outward normal."""
    qx = np.abs(X) - hx
    qy = np.abs(Y) - hy
    ox = np.maximum(qx, 0.0)
    oy = np.maximum(qy, 0.0)
    outside = np.hypot(ox, oy)
    d = outside + np.minimum(np.maximum(qx, qy), 0.0)
    is_out = outside > 0.0
    xdom = qx >= qy
    nx = np.where(is_out, ox, np.where(xdom, 1.0, 0.0))
    ny = np.where(is_out, oy, np.where(xdom, 0.0, 1.0))
    nx[X < 0] *= -1.0
    ny[Y < 0] *= -1.0
    return d, nx, ny


def render_scene(
    camera: CameraModel,
    plate: DotPlate,
    T_cam_plate: np.ndarray,
    conditions: ImagingConditions,
    *,
    extra_distortion: ExtraDistortion | Sequence[float] | None = None,
    blur: bool = True,
    tile_px: int = TILE_PX,
) -> np.ndarray:
    """Noise-free, gain-free radiance image (H, W) float32 in DN: pixel-area coverage of the
    dots and plate, optionally blurred (base + defocus).  Building block of
    :func:`render_plate_image`; useful for tests that need sub-DN precision."""
    T = _check_pose(T_cam_plate)
    Tp = int(tile_px)
    grid = undistortion_grid(camera, extra_distortion, Tp)
    nty, ntx = grid.nty, grid.ntx
    L_plate, L_dot = conditions.plate_and_dot_levels(plate)
    L_bg = conditions.background_level if plate.margin_mm > 0 else L_plate
    finite = plate.margin_mm > 0
    hx, hy = plate.half_extent_mm
    R = plate.dot_diameter_mm / 2.0

    # homography normalised image (x, y, 1) -> plate (X, Y, 1) / Z
    H = np.column_stack([T[:3, 0], T[:3, 1], T[:3, 3]])
    if abs(float(np.dot(T[:3, 2], T[:3, 3]))) < 1e-9 * max(1.0, float(np.linalg.norm(T[:3, 3]))):
        # the plate plane contains the projection centre: seen exactly edge-on, nothing visible
        return np.full((camera.height_px, camera.width_px), L_bg, np.float32)
    Hi = np.linalg.inv(H)

    def to_plate(xy):
        x, y = xy[..., 0], xy[..., 1]
        w = Hi[2, 0] * x + Hi[2, 1] * y + Hi[2, 2]
        iw = 1.0 / np.where(w > 0, w, np.nan)
        return (
            (Hi[0, 0] * x + Hi[0, 1] * y + Hi[0, 2]) * iw,
            (Hi[1, 0] * x + Hi[1, 1] * y + Hi[1, 2]) * iw,
            iw,
        )

    # --- tile classification from the corner nodes -----------------------------------------
    NX, NY, NZ = to_plate(grid.corner_nodes())  # (nty+1, ntx+1); NaN where the ray misses
    c00 = (NX[:-1, :-1], NY[:-1, :-1])
    c01 = (NX[:-1, 1:], NY[:-1, 1:])
    c10 = (NX[1:, :-1], NY[1:, :-1])
    c11 = (NX[1:, 1:], NY[1:, 1:])
    PX = 0.25 * (c00[0] + c01[0] + c10[0] + c11[0])
    PY = 0.25 * (c00[1] + c01[1] + c10[1] + c11[1])
    rho = np.sqrt(np.maximum.reduce([(c[0] - PX) ** 2 + (c[1] - PY) ** 2 for c in (c00, c01, c10, c11)]))
    # Jacobian d(X, Y)/d(u, v) per tile (mm/px)
    dXdu = 0.5 * ((c01[0] - c00[0]) + (c11[0] - c10[0])) / Tp
    dYdu = 0.5 * ((c01[1] - c00[1]) + (c11[1] - c10[1])) / Tp
    dXdv = 0.5 * ((c10[0] - c00[0]) + (c11[0] - c01[0])) / Tp
    dYdv = 0.5 * ((c10[1] - c00[1]) + (c11[1] - c01[1])) / Tp
    # σ (px) rendered analytically into the edges: per tile, the largest at its corners
    Z_nodes = np.where(np.isfinite(NZ), NZ, camera.focus_distance_mm)
    s_nodes = blur_sigma_px(camera, conditions, Z_nodes) if blur else np.zeros_like(Z_nodes)  # total σ
    s_tile = np.minimum(np.maximum.reduce([s_nodes[:-1, :-1], s_nodes[:-1, 1:], s_nodes[1:, :-1], s_nodes[1:, 1:]]),
                        ANALYTIC_BLUR_MAX_PX)
    edge_reach_px = 1.5 + 4.0 * s_tile  # the pixel's half-diagonal and the blur's tails
    reach = 1.1 * rho + edge_reach_px * np.sqrt(dXdu**2 + dYdu**2 + dXdv**2 + dYdv**2) + 1e-9

    valid = np.isfinite(PX) & np.isfinite(reach)
    any_valid = (
        np.isfinite(NX[:-1, :-1]) | np.isfinite(NX[:-1, 1:]) | np.isfinite(NX[1:, :-1]) | np.isfinite(NX[1:, 1:])
    )
    PXs = np.where(valid, PX, 0.0)
    PYs = np.where(valid, PY, 0.0)
    reach = np.where(valid, reach, 0.0)
    _, _, dd = _nearest_dot_distance(PXs, PYs, plate)
    if finite:
        de, _, _ = _box_signed_distance(PXs, PYs, hx, hy)
        edge_near = valid & (np.abs(de) < reach)
        outside = valid & (de >= reach)
    else:
        edge_near = np.zeros_like(valid)
        outside = np.zeros_like(valid)
    dot_near = valid & ~outside & (np.abs(dd - R) < reach)
    in_dot = valid & ~outside & (dd + reach <= R)
    if not plate_faces_camera(T):  # seen from behind: a blank plate
        dot_near[...] = False
        in_dot[...] = False
    fine = dot_near | edge_near | (any_valid & ~valid)

    tile_val = np.full((nty, ntx), L_bg, np.float32)
    tile_val[valid & ~outside] = L_plate
    tile_val[in_dot] = L_dot
    canvas = np.empty((nty * Tp, ntx * Tp), np.float32)
    tv = _tile_view(canvas, Tp)
    tv[...] = tile_val[:, :, None, None]

    ti, tj = np.nonzero(fine)
    if ti.size:
        X, Y, Zp = to_plate(grid.tiles(ti, tj))  # (N, T, T) mm, NaN where the ray misses
        ok = np.isfinite(X)
        all_ok = bool(ok.all())
        if not all_ok:
            X[~ok] = 0.0
            Y[~ok] = 0.0
            Zp[~ok] = camera.focus_distance_mm
        if blur:
            sigma = np.minimum(blur_sigma_px(camera, conditions, Zp), ANALYTIC_BLUR_MAX_PX)
        else:
            sigma = np.zeros(X.shape)
        J = np.clip(np.nan_to_num(np.stack([dXdu, dYdu, dXdv, dYdv])[:, ti, tj]), -1e6, 1e6)
        J = J.astype(np.float32)[:, :, None, None]  # 4 × (N, 1, 1), mm/px (clipped: grazing views)

        def coverage(sub, d_mm, nx, ny, radius_mm=None):
            """Pixel value (0–1) of the inner side of an edge at signed distance d_mm (mm,
            positive outside) with outward normal (nx, ny) (plate axes, any length) for tiles
            ``sub``, blurred by the tiles' analytic σ.  ``radius_mm``: the edge is a circle of
            this radius; blurring moves it inwards by σ²/(2ρ) (ρ: its radius in px)."""
            jxu, jyu, jxv, jyv = J[:, sub]
            gu = jxu * nx + jyu * ny  # ∇_uv d · |n|  (chain rule, J^T n)
            gv = jxv * nx + jyv * ny
            gn = np.maximum(np.hypot(gu, gv), np.float32(1e-30))
            nn = np.hypot(nx, ny)
            # d_px = d_mm / |J^T n̂| = d_mm · |n| / |J^T n|
            t_in = -d_mm * nn / gn
            s = sigma[sub]
            if radius_mm is not None:
                t_in = t_in - s * s * gn / (2.0 * radius_mm * np.maximum(nn, np.float32(1e-30)))
            return _blurred_edge_coverage(t_in, gu, gv, s)

        dc = np.broadcast_to(in_dot[ti, tj].astype(np.float32)[:, None, None], X.shape).copy()
        sub = np.nonzero(dot_near[ti, tj])[0]
        if sub.size:
            dx, dy, dist = _nearest_dot_distance(X[sub], Y[sub], plate)
            dx[dist == 0.0] = 1.0  # any direction will do at the exact centre
            dc[sub] = coverage(sub, (dist - R).astype(np.float32), dx.astype(np.float32), dy.astype(np.float32),
                               radius_mm=R)
        pc = np.ones_like(dc)
        if finite:
            sub = np.nonzero(edge_near[ti, tj] | ~ok.all(axis=(1, 2)))[0]
            if sub.size:
                de, nx, ny = _box_signed_distance(X[sub], Y[sub], hx, hy)
                pc[sub] = coverage(sub, de.astype(np.float32), nx.astype(np.float32), ny.astype(np.float32))
        if not all_ok:
            pc[~ok] = 0.0
        # value = bg + pc · ((plate − bg) + dc · (dot − plate))
        dc *= np.float32(L_dot - L_plate)
        dc += np.float32(L_plate - L_bg)
        dc *= pc
        dc += np.float32(L_bg)
        tv[ti, tj] = dc

    if blur:
        _apply_blur(canvas, fine, s_nodes, Tp)
    return canvas[: camera.height_px, : camera.width_px]


def _gaussian_blur(src: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur (σ px, reflecting borders).  For σ ≥ 4 the work is done on a ``f``× block-
    averaged copy (f = 2^⌊log2(σ/2)⌋) and linearly upsampled, with the blur reduced so that
    box + Gaussian + tent variances add up to σ² (first moments exact, σ within ~5 %)."""
    if sigma <= 0.0:
        return src.copy()
    if sigma < 4.0:
        return cv2.GaussianBlur(src, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    f = 2 ** math.floor(math.log2(sigma / 2.0))
    h, w = src.shape
    ph, pw = -h % f, -w % f
    if ph or pw:
        src = cv2.copyMakeBorder(src, 0, ph, 0, pw, cv2.BORDER_REFLECT)
    small = cv2.resize(src, ((w + pw) // f, (h + ph) // f), interpolation=cv2.INTER_AREA)
    # per axis: block f²/12, linear interpolation f²/6 on average, so σ_small² f² = σ² − f²/4
    s_small = math.sqrt(sigma * sigma - f * f / 4.0) / f
    small = cv2.GaussianBlur(small, (0, 0), s_small, borderType=cv2.BORDER_REFLECT)
    big = cv2.resize(small, (w + pw, h + ph), interpolation=cv2.INTER_LINEAR)
    return big[:h, :w]


def _apply_blur(canvas, fine, s_nodes, Tp):
    """Blur ``canvas`` in place where it is not locally uniform (near ``fine`` tiles).

    σ (px) is what the edges do not already carry, √(σ_total² − ``ANALYTIC_BLUR_MAX_PX``²), with
    σ_total (``s_nodes``) from the plate depth at the tile corners (:func:`blur_sigma_px`).  If it
    is uniform to 2 % over the region, one Gaussian; otherwise levels spaced by ×1.25 in σ,
    each blurring only the tiles that need it, blended per pixel linearly in σ² (so the blended
    kernel has exactly the local variance).
    """
    if not fine.any():
        return
    s2n = np.minimum(s_nodes, MAX_BLUR_SIGMA_PX) ** 2  # σ² at tile corners
    s2n = np.maximum(s2n - ANALYTIC_BLUR_MAX_PX**2, 0.0)  # what the analytic edges lack
    smax_all = float(np.sqrt(s2n.max()))
    if smax_all < 1e-3:
        return
    hc, wc = canvas.shape
    nty, ntx = fine.shape
    rt = math.ceil((4.0 * smax_all + 2.0) / Tp)  # blur reach in tiles
    fi, fj = np.nonzero(fine)
    bi0, bi1 = max(fi.min() - rt, 0), min(fi.max() + rt + 1, nty)
    bj0, bj1 = max(fj.min() - rt, 0), min(fj.max() + rt + 1, ntx)
    box = s2n[bi0 : bi1 + 1, bj0 : bj1 + 1]
    s_lo, s_hi = math.sqrt(float(box.min())), math.sqrt(float(box.max()))

    if s_hi <= max(s_lo * 1.02, s_lo + 0.01):  # one level: blur the box around the fine tiles
        sk = 0.5 * (s_lo + s_hi)
        pad = math.ceil(4.0 * sk) + 1
        i0, i1, j0, j1 = bi0 * Tp, bi1 * Tp, bj0 * Tp, bj1 * Tp
        y0, y1, x0, x1 = max(i0 - pad, 0), min(i1 + pad, hc), max(j0 - pad, 0), min(j1 + pad, wc)
        b = _gaussian_blur(canvas[y0:y1, x0:x1], sk)
        canvas[i0:i1, j0:j1] = b[i0 - y0 : i1 - y0, j0 - x0 : j1 - x0]
        return

    # several levels: only tiles within blur reach of a fine tile
    act = cv2.dilate(fine.astype(np.uint8), np.ones((2 * rt + 1, 2 * rt + 1), np.uint8)).astype(bool)
    ai, aj = np.nonzero(act)
    t00, t01, t10, t11 = (
        a.astype(np.float32) for a in (s2n[ai, aj], s2n[ai, aj + 1], s2n[ai + 1, aj], s2n[ai + 1, aj + 1])
    )
    t_lo = np.sqrt(np.minimum(np.minimum(t00, t01), np.minimum(t10, t11)))
    t_hi = np.sqrt(np.maximum(np.maximum(t00, t01), np.maximum(t10, t11)))
    s_lo, s_hi = float(t_lo.min()), float(t_hi.max())
    ratio = 1.25
    s_first = max(s_lo, 0.25)  # below this, blend with no blur at all (level σ = 0)
    n = math.ceil(math.log(max(s_hi, s_first * ratio) / s_first) / math.log(ratio)) + 1
    levels = np.geomspace(s_first, max(s_hi, s_first * ratio), max(n, 2))
    if s_lo < s_first:
        levels = np.concatenate([[0.0], levels])
    L2 = (levels**2).astype(np.float32)
    # per-pixel σ², bilinear between the tile corners: (N_active, T, T)
    f = ((np.arange(Tp) + 0.5) / Tp).astype(np.float32)
    fy, fx = f[:, None], f[None, :]
    s2p = t00[:, None, None] * ((1 - fy) * (1 - fx))
    s2p += t01[:, None, None] * ((1 - fy) * fx)
    s2p += t10[:, None, None] * (fy * (1 - fx))
    s2p += t11[:, None, None] * (fy * fx)
    np.clip(s2p, L2[0], L2[-1], out=s2p)
    out = np.zeros((ai.size, Tp, Tp), np.float32)
    for k, sk in enumerate(levels):
        lo_k = levels[k - 1] if k > 0 else -np.inf
        hi_k = levels[k + 1] if k + 1 < levels.size else np.inf
        sel = np.nonzero((t_hi > lo_k) & (t_lo < hi_k))[0]
        if not sel.size:
            continue
        bt = np.empty((sel.size, Tp, Tp), np.float32)
        pad = math.ceil(4.0 * sk) + 1
        # blur in horizontal strips of STRIP tile rows: keeps diagonal bands cheap
        strip = ai[sel] // _BLUR_STRIP_TILES
        for st in np.unique(strip):
            m = np.nonzero(strip == st)[0]
            si, sj = ai[sel[m]], aj[sel[m]]
            i0, i1, j0, j1 = si.min(), si.max() + 1, sj.min(), sj.max() + 1
            y0, y1 = max(i0 * Tp - pad, 0), min(i1 * Tp + pad, hc)
            x0, x1 = max(j0 * Tp - pad, 0), min(j1 * Tp + pad, wc)
            b = _gaussian_blur(canvas[y0:y1, x0:x1], float(sk))
            bv = _tile_view(b[i0 * Tp - y0 : i1 * Tp - y0, j0 * Tp - x0 : j1 * Tp - x0], Tp)
            bt[m] = bv[si - i0, sj - j0]
        # hat weight of level k, linear in σ²
        s2 = s2p[sel]
        w = np.ones_like(s2)
        if k > 0:
            np.minimum(w, (s2 - L2[k - 1]) / (L2[k] - L2[k - 1]), out=w)
        if k + 1 < levels.size:
            np.minimum(w, (L2[k + 1] - s2) / (L2[k + 1] - L2[k]), out=w)
        np.maximum(w, np.float32(0.0), out=w)
        w *= bt
        out[sel] += w
    _tile_view(canvas, Tp)[ai, aj] = out


@lru_cache(maxsize=1)
def _normal_table() -> np.ndarray:
    """65536 equiprobable standard-normal quantiles (inverse CDF at (k + ½)/65536), float32,
    rescaled to unit variance exactly.  Tails are cut at ±4.3σ."""
    from statistics import NormalDist

    inv = NormalDist().inv_cdf
    t = np.array([inv((k + 0.5) / 65536.0) for k in range(65536)], dtype=np.float64)
    t /= np.sqrt(np.mean(t * t))
    t = t.astype(np.float32)
    t.setflags(write=False)
    return t


def standard_normal_image(rng: np.random.Generator, shape) -> np.ndarray:
    """Standard normal deviates (float32) by 16-bit inverse-CDF lookup: ~3× faster than
    ``rng.standard_normal`` for a full frame, indistinguishable at 8-bit image noise levels
    (65536 quantiles, tails truncated at ±4.3σ).  Deterministic given the generator state."""
    idx = rng.integers(0, 65536, size=shape, dtype=np.uint16)
    return _normal_table()[idx]


def render_plate_image(
    camera: CameraModel,
    plate: DotPlate,
    T_cam_plate: np.ndarray,
    conditions: ImagingConditions,
    seed: int,
    *,
    extra_distortion: ExtraDistortion | Sequence[float] | None = None,
    noiseless: bool = False,
) -> np.ndarray:
    """Render the camera image (H, W) uint8 of ``plate`` at pose ``T_cam_plate``.

    camera: intrinsics of this image (per-image intrinsics are fine: grids are keyed by exact
        parameters).  T_cam_plate: 4×4, plate frame (mm) → camera frame (mm).
    conditions: photometry/optics, see :class:`ImagingConditions`.
    seed: seeds ``numpy.random.default_rng``; same inputs and seed → byte-identical image.
    extra_distortion: optional :class:`ExtraDistortion` (or a 5-sequence k4, s1, s2, s3, s4)
        applied on top of ``camera.distortion``.
    noiseless: skip read and shot noise (gain maps and 8-bit quantisation still applied).
    """
    img = render_scene(camera, plate, T_cam_plate, conditions, extra_distortion=extra_distortion)
    img = np.ascontiguousarray(img)  # a view of the tile canvas; copied only if it was padded
    if conditions.vignetting != 0.0 or conditions.gradient != 0.0:
        np.multiply(img, gain_map(camera, conditions), out=img)
    if not noiseless:
        noise = standard_normal_image(np.random.default_rng(seed), img.shape)
        gain_e = conditions.shot_noise_gain_e_per_dn
        read2 = np.float32(conditions.read_noise_dn**2)
        if gain_e is not None and gain_e > 0:
            sd = np.maximum(img, np.float32(0.0))
            sd *= np.float32(1.0 / gain_e)
            sd += read2
            np.sqrt(sd, out=sd)
            noise *= sd
        else:
            noise *= np.sqrt(read2)
        img += noise
    np.rint(img, out=img)
    np.clip(img, 0.0, 255.0, out=img)
    return img.astype(np.uint8)
