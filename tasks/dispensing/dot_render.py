"""Images of adhesive dots in black ring targets, as camera 1 sees them, with their truth.

Simulator side. A scene is drawn in millimetres around the ring centre and mapped to the pixels
of an image crop (a region of interest of the full-resolution sensor) by an affine map: the local
projection of the camera at the ring (over a few millimetres at the image centre the distortion's
change is far below a thousandth of a pixel). Each pixel integrates the scene over a 5 × 5
sub-pixel grid; optical blur (Gaussian), a slight illumination gradient and sensor noise (read
noise plus shot noise) follow, rounded to 8 bits.

An adhesive dot is a closed curve r(θ) = R (1 + e cos 2(θ − φ) + Σ_k a_k cos(kθ + φ_k)), k = 3…12
(edge roughness); its grey level is flat but for a faint dome (the drop's lens); it is brighter or
darker than the substrate (the lighting decides: the seed's dots are bright under its ring light,
transmissive UV adhesive on a dark substrate is darker), inside a black ring. Defects: a
``satellite`` (a second small drop next to it), a ``void`` (a bubble: a hole through the dot), a
``smear`` (the drop dragged: elongated and off the tip), a ``missing`` dot. The truth keeps the
tip's foot (where the dot is centred unless smeared), the equivalent diameter of the drawn curve,
its NSD_r and its class.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

DEFECTS = ("satellite", "void", "smear", "missing")
SUPERSAMPLE = 5


@dataclass(frozen=True)
class DotShape:
    """One dot in the ring's frame (mm; x, y of the workpiece surface, origin at the ring centre).

    centre_mm: where the tip was (the dot's centre unless smeared). radius_mm: R. ellipticity: e;
    angle_rad: φ. roughness: (k, amplitude, phase) rows. defect: "" or one of :data:`DEFECTS`.
    extra: defect geometry (satellite/void: centre offset (mm) and radius (mm); smear: stretch
    factor, direction (rad))."""

    centre_mm: tuple[float, float]
    radius_mm: float
    ellipticity: float = 0.0
    angle_rad: float = 0.0
    roughness: tuple[tuple[float, float, float], ...] = ()
    defect: str = ""
    extra: dict = field(default_factory=dict)

    def reach_mm(self) -> float:
        """A radius about the centre beyond which the dot, defects included, covers nothing (mm)."""
        r = self.radius_mm * (1.0 + self.ellipticity + sum(abs(a) for _, a, _ in self.roughness))
        if self.defect == "smear":
            r *= 1.0 + self.extra["stretch"]
        if self.defect == "satellite":
            r = max(r, float(np.hypot(*self.extra["offset_mm"])) + self.extra["radius_mm"])
        return r

    def boundary_radius(self, theta: np.ndarray) -> np.ndarray:
        """r(θ) (mm) of the undefected outline."""
        r = 1.0 + self.ellipticity * np.cos(2 * (theta - self.angle_rad))
        for k, a, ph in self.roughness:
            r = r + a * np.cos(k * theta + ph)
        return self.radius_mm * r

    def _local(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Coordinates relative to the outline's centre, smear undone (stretched back to the drop)."""
        dx, dy = x - self.centre_mm[0], y - self.centre_mm[1]
        if self.defect == "smear":
            s, psi = self.extra["stretch"], self.extra["direction_rad"]
            c, n = np.cos(psi), np.sin(psi)
            along, across = dx * c + dy * n, -dx * n + dy * c
            along = (along - 0.5 * (s - 1.0) * self.radius_mm) / s  # stretched and dragged along psi
            dx, dy = along * c - across * n, along * n + across * c
        return dx, dy

    def coverage(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """1 where the adhesive covers the surface point (x, y) (mm, ring frame), else 0."""
        if self.defect == "missing":
            return np.zeros_like(x)
        dx, dy = self._local(x, y)
        inside = np.hypot(dx, dy) < self.boundary_radius(np.arctan2(dy, dx))
        if self.defect == "void":
            (vx, vy), rv = self.extra["offset_mm"], self.extra["radius_mm"]
            inside &= np.hypot(dx - vx, dy - vy) >= rv
        if self.defect == "satellite":
            (sx, sy), rs = self.extra["offset_mm"], self.extra["radius_mm"]
            inside |= np.hypot(dx - sx, dy - sy) < rs
        return inside.astype(float)

    def equivalent_diameter_mm(self) -> float:
        """sqrt(4 A / π) of the undefected outline, A = ½ ∮ r² dθ."""
        theta = np.linspace(0, 2 * np.pi, 4096, endpoint=False)
        area = 0.5 * np.mean(self.boundary_radius(theta) ** 2) * 2 * np.pi
        return float(np.sqrt(4 * area / np.pi))

    def nsd_r(self) -> float:
        """NSD_r (§4.3) of the undefected outline: σ_r / μ_r of the radii from its centroid,
        points spaced evenly along the outline."""
        theta = np.linspace(0, 2 * np.pi, 4096, endpoint=False)
        r = self.boundary_radius(theta)
        x, y = r * np.cos(theta), r * np.sin(theta)
        seg = np.hypot(np.roll(x, -1) - x, np.roll(y, -1) - y)
        w = seg / seg.sum()
        cross = x * np.roll(y, -1) - np.roll(x, -1) * y
        area = 0.5 * cross.sum()
        cx = ((x + np.roll(x, -1)) * cross).sum() / (6 * area)
        cy = ((y + np.roll(y, -1)) * cross).sum() / (6 * area)
        rho = np.hypot(x - cx, y - cy)
        mu = (w * rho).sum()
        return float(np.sqrt((w * (rho - mu) ** 2).sum()) / mu)


@dataclass(frozen=True)
class Lighting:
    """Grey levels (DN) and image quality of a crop.

    substrate, ring: levels of the bare surface and the printed ring; contrast: dot − substrate
    (positive: bright dots, negative: dark ones); dome: the dot's centre-to-edge rise as a fraction
    of the contrast; gradient: illumination change across the crop (DN); blur_px: optical blur σ;
    read_noise, gain_e_per_dn: sensor noise (variance read² + level / gain)."""

    substrate: float = 150.0
    ring: float = 25.0
    contrast: float = 40.0
    dome: float = 0.08
    gradient: float = 3.0
    blur_px: float = 1.0
    read_noise: float = 1.5
    gain_e_per_dn: float = 20.0


@dataclass(frozen=True)
class RingScene:
    """A ring with its dot(s) mapped into an image crop.

    ring_px: (2,) pixel position of the ring centre in the crop; mm_to_px: (2, 2) the local
    projection (px per mm; columns: the workpiece x and y); ring_inner_mm/ring_outer_mm:
    diameters (mm); dots: the adhesive (0, 1 or 2 of them)."""

    ring_px: tuple[float, float]
    mm_to_px: np.ndarray
    ring_inner_mm: float
    ring_outer_mm: float
    dots: tuple[DotShape, ...] = ()

    def dot_px(self, dot: DotShape) -> np.ndarray:
        """(2,) pixel position of a dot's centre (where the tip was)."""
        return np.asarray(self.ring_px) + self.mm_to_px @ np.asarray(dot.centre_mm)


def render_scene(scene: RingScene, shape: tuple[int, int], lighting: Lighting, rng: np.random.Generator
                 ) -> np.ndarray:
    """The 8-bit crop (rows, cols) of ``scene`` under ``lighting``."""
    h, w = shape
    s = (np.arange(SUPERSAMPLE) + 0.5) / SUPERSAMPLE - 0.5
    # pixel (col, row) centres at integer coordinates, as OpenCV counts them
    u = (np.arange(w)[:, None] + s[None, :]).ravel()
    v = (np.arange(h)[:, None] + s[None, :]).ravel()
    uu, vv = np.meshgrid(u, v)
    inv = np.linalg.inv(scene.mm_to_px)
    du, dv = uu - scene.ring_px[0], vv - scene.ring_px[1]
    x, y = (inv[0, 0] * du + inv[0, 1] * dv).ravel(), (inv[1, 0] * du + inv[1, 1] * dv).ravel()
    rho = np.hypot(x, y)
    level = np.full(x.shape, lighting.substrate)
    ring = (rho >= 0.5 * scene.ring_inner_mm) & (rho <= 0.5 * scene.ring_outer_mm)
    level[ring] = lighting.ring
    for dot in scene.dots:
        near = np.flatnonzero(np.hypot(x - dot.centre_mm[0], y - dot.centre_mm[1]) < dot.reach_mm())
        cover = near[dot.coverage(x[near], y[near]) > 0]
        dx, dy = dot._local(x[cover], y[cover])
        fall = np.clip(np.hypot(dx, dy) / dot.radius_mm, 0, 1) ** 2
        level[cover] = lighting.substrate + lighting.contrast * (1.0 + lighting.dome * (1.0 - fall))
    image = level.reshape(h, SUPERSAMPLE, w, SUPERSAMPLE).mean(axis=(1, 3))
    if lighting.blur_px > 0:
        image = cv2.GaussianBlur(image, (0, 0), lighting.blur_px, borderType=cv2.BORDER_REFLECT)
    cols = np.linspace(-0.5, 0.5, w)[None, :]
    image = image + lighting.gradient * cols
    var = lighting.read_noise ** 2 + np.maximum(image, 0) / lighting.gain_e_per_dn
    image = image + rng.normal(size=image.shape) * np.sqrt(var)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def random_dot(rng: np.random.Generator, centre_mm, diameter_mm: float, defect: str = "",
               diameter_scatter: float = 0.03, max_ellipticity: float = 0.03, roughness: float = 0.004
               ) -> DotShape:
    """A dot centred on ``centre_mm`` (mm, ring frame) with the scatter of a dispenser: diameter
    (relative σ ``diameter_scatter``), ellipticity up to ``max_ellipticity``, edge roughness (rms
    relative amplitude ``roughness`` spread over harmonics 3–12), and a defect's geometry."""
    radius = 0.5 * diameter_mm * (1.0 + diameter_scatter * rng.standard_normal())
    ks = np.arange(3, 13)
    amps = rng.standard_normal(len(ks)) * roughness / np.sqrt(len(ks) / 2)
    rough = tuple((float(k), float(a), float(p)) for k, a, p in zip(ks, amps, rng.uniform(0, 2 * np.pi, len(ks)),
                                                                      strict=True))
    extra: dict = {}
    direction = rng.uniform(0, 2 * np.pi)
    unit = np.array([np.cos(direction), np.sin(direction)])
    if defect == "satellite":
        extra = {"radius_mm": radius * rng.uniform(0.25, 0.35),
                 "offset_mm": tuple(unit * radius * rng.uniform(1.7, 2.0))}
    elif defect == "void":
        extra = {"radius_mm": radius * rng.uniform(0.3, 0.45), "offset_mm": tuple(unit * radius * rng.uniform(0, 0.25))}
    elif defect == "smear":
        extra = {"stretch": rng.uniform(1.5, 2.0), "direction_rad": direction}
    elif defect not in ("", "missing"):
        raise ValueError(f"unknown dot defect {defect!r}; known: {', '.join(DEFECTS)}")
    return DotShape(centre_mm=(float(centre_mm[0]), float(centre_mm[1])), radius_mm=float(radius),
                    ellipticity=float(rng.uniform(0, max_ellipticity)), angle_rad=float(rng.uniform(0, np.pi)),
                    roughness=rough, defect=defect, extra=extra)


def draw_defect(rng: np.random.Generator, rate: float) -> str:
    """"" (a good dot) or a defect class drawn with total probability ``rate``, classes alike."""
    return str(rng.choice(DEFECTS)) if rng.uniform() < rate else ""
