"""Trays of boards to glue, rendered as the paper's camera sees them (§2.1, §4.1.2), with truth.

A tray (a black anti-static carrier, ``rows`` × ``cols`` pockets) holds one small board per pocket,
placed by hand: shifted inside its pocket and turned by any angle. Each board carries the paper's
dispensing target, a 4 × 2 mm capacitor (§3.2.1), beside things that are bright in the R channel but
are not the target (silkscreen marks, a fiducial, a smaller 0805 part with silver ends, the bare pads
under the capacitor). The solder mask is one of several greens or a blue. A share of boards is
defective: a broken edge (a bite out of the board's outline) or the capacitor missing (bare pads).

Frames and units:

* tray frame (mm): origin at the tray's centre, x to the right of the image, y up (up the image).
  Placed on the C table in plate a's place it is the machine's workpiece frame.
* image pixels: u right, v down, origin at the centre of the top-left pixel. The rendered image is the
  tray seen straight from above at ``mm_per_px`` (the planar view, the paper's assumption):
  u = cu + x / s, v = cv − y / s with (cu, cv) the image centre.
* angles (deg) are counter-clockwise in the tray frame (clockwise on the screen, v being down);
  an area's angle is its long axis', in [0, 180).

The light is the paper's ring light: a radial fall-off of the illumination towards the image corners,
specular glare spots on the boards, dust, sensor noise. Edges are antialiased by exact coverage of a
signed distance (the coverage of every feature is symmetric about its centre, so the truth centre is
the centre of the rendered pixels' mass).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import pandas as pd

# colours (R, G, B), 0–255
TRAY_RGB = (24, 24, 27)
MASK_RGB = {"green": (40, 112, 52), "dark green": (22, 72, 38), "olive green": (55, 95, 40), "blue": (28, 58, 120)}
CAPACITOR_BODY_RGB = (214, 178, 120)
TERMINATION_RGB = (198, 198, 196)
PAD_RGB = (182, 180, 172)
SILK_RGB = (232, 232, 228)
PART_BODY_RGB = (32, 32, 34)
DEFECTS = ("broken_edge", "missing_component")


@dataclass(frozen=True)
class TraySpec:
    """A tray and its boards (lengths in mm, angles in deg). ``mm_per_px``: the planar image scale
    (camera 1 of the prototype sees 0.045 mm per pixel at its 300 mm working distance);
    ``image_px``: (width, height) of the rendered image (the paper's camera: 2448 × 2048).
    ``component_offset_mm``: the capacitor's centre in the board frame (x along the board's long side).
    ``defect_rate``: share of defective boards, half with a broken edge, half without the capacitor."""

    rows: int = 4
    cols: int = 5
    pocket_mm: float = 21.0
    board_mm: tuple[float, float] = (16.0, 12.0)
    component_mm: tuple[float, float] = (4.0, 2.0)
    component_offset_mm: tuple[float, float] = (2.5, 1.5)
    position_jitter_mm: float = 1.0
    defect_rate: float = 0.1
    mm_per_px: float = 0.045
    image_px: tuple[int, int] = (2448, 2048)
    glare_spots: int = 4
    dust_specks: int = 60
    noise_dn: float = 2.0

    def to_dict(self) -> dict:
        return asdict(self)

    @property
    def size_mm(self) -> tuple[float, float]:
        """(width, height) of the pocket grid (mm)."""
        return self.cols * self.pocket_mm, self.rows * self.pocket_mm


def image_centre(spec: TraySpec) -> tuple[float, float]:
    """(cu, cv): the pixel of the tray's origin in the planar image."""
    return (spec.image_px[0] - 1) / 2.0, (spec.image_px[1] - 1) / 2.0


def tray_to_pixels(spec: TraySpec, xy_mm: np.ndarray) -> np.ndarray:
    """(N, 2) planar image pixels (u, v) of tray-frame points (N, 2) (mm)."""
    cu, cv = image_centre(spec)
    xy = np.asarray(xy_mm, dtype=float).reshape(-1, 2)
    return np.column_stack([cu + xy[:, 0] / spec.mm_per_px, cv - xy[:, 1] / spec.mm_per_px])


def pixels_to_tray(spec: TraySpec, uv: np.ndarray) -> np.ndarray:
    """(N, 2) tray-frame points (mm) of planar image pixels (N, 2): the inverse of :func:`tray_to_pixels`."""
    cu, cv = image_centre(spec)
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    return np.column_stack([(uv[:, 0] - cu) * spec.mm_per_px, (cv - uv[:, 1]) * spec.mm_per_px])


def _rot(theta_rad: float) -> np.ndarray:
    c, s = np.cos(theta_rad), np.sin(theta_rad)
    return np.array([[c, -s], [s, c]])


def _box_sdf(px: np.ndarray, py: np.ndarray, cx: float, cy: float, hx: float, hy: float) -> np.ndarray:
    """Signed distance (mm, negative inside) to the axis-aligned box of centre (cx, cy), half sizes (hx, hy)."""
    qx, qy = np.abs(px - cx) - hx, np.abs(py - cy) - hy
    outside = np.hypot(np.maximum(qx, 0.0), np.maximum(qy, 0.0))
    return outside + np.minimum(np.maximum(qx, qy), 0.0)


def _disc_sdf(px: np.ndarray, py: np.ndarray, cx: float, cy: float, r: float) -> np.ndarray:
    return np.hypot(px - cx, py - cy) - r


def _coverage(sdf_mm: np.ndarray, mm_per_px: float) -> np.ndarray:
    """Share of a pixel inside a shape from the signed distance at its centre (exact for a straight edge
    along a pixel axis; symmetric about the edge at any angle)."""
    return np.clip(0.5 - sdf_mm / mm_per_px, 0.0, 1.0)


@dataclass(frozen=True)
class Board:
    """One placed board: centre (mm, tray frame), angle (deg), solder-mask colour, defect ('' when
    intact) and, for a broken edge, the bite (centre in the board frame, radius; mm)."""

    board_id: str
    row: int
    col: int
    x_mm: float
    y_mm: float
    angle_deg: float
    mask: str
    mask_rgb: tuple[int, int, int]
    defect: str
    bite: tuple[float, float, float] = (0.0, 0.0, 0.0)


def place_boards(spec: TraySpec, rng: np.random.Generator, boards: int | None = None) -> list[Board]:
    """The boards of a tray: one per pocket (the first ``boards`` pockets row by row when given), any
    angle, shifted by up to ``position_jitter_mm`` each way as far as the pocket's walls let it, a
    random mask colour (each channel jittered by up to ±8), a defect with probability ``defect_rate``."""
    n = spec.rows * spec.cols if boards is None else boards
    if n > spec.rows * spec.cols:
        raise ValueError(f"{n} boards do not fit a tray of {spec.rows} × {spec.cols} pockets")
    names = list(MASK_RGB)
    hx, hy = spec.board_mm[0] / 2, spec.board_mm[1] / 2
    out = []
    for k in range(n):
        r, c = divmod(k, spec.cols)
        angle = float(rng.uniform(0, 360))
        # the board stays inside its pocket (0.25 mm from the walls): the shift it has room for at this angle
        t = np.deg2rad(angle)
        ext = np.array([hx * abs(np.cos(t)) + hy * abs(np.sin(t)), hx * abs(np.sin(t)) + hy * abs(np.cos(t))])
        room = np.clip(spec.pocket_mm / 2 - 0.25 - ext, 0.0, spec.position_jitter_mm)
        x = (c - (spec.cols - 1) / 2) * spec.pocket_mm + rng.uniform(-1, 1) * room[0]
        y = ((spec.rows - 1) / 2 - r) * spec.pocket_mm + rng.uniform(-1, 1) * room[1]
        mask = names[rng.integers(len(names))]
        rgb = tuple(int(np.clip(v + rng.integers(-8, 9), 0, 255)) for v in MASK_RGB[mask])
        defect = ""
        if rng.uniform() < spec.defect_rate:
            defect = DEFECTS[rng.integers(2)]
        bite = (0.0, 0.0, 0.0)
        if defect == "broken_edge":  # on the half away from the capacitor (x < −2 in the board frame)
            radius = rng.uniform(1.5, 3.0)
            side = rng.integers(3)
            if side == 0:
                bite = (-hx, rng.uniform(-hy + 1, hy - 1), radius)
            else:
                bite = (rng.uniform(-hx + 1, -2.0), hy if side == 1 else -hy, radius)
        out.append(Board(f"b{k:02d}", r, c, float(x), float(y), angle, mask, rgb, defect,
                         tuple(float(v) for v in bite)))
    return out


def _board_layers(spec: TraySpec, board: Board, lx: np.ndarray, ly: np.ndarray):
    """(coverage, rgb) layers of one board in painting order, on board-frame coordinates (mm)."""
    hx, hy = spec.board_mm[0] / 2, spec.board_mm[1] / 2
    s = spec.mm_per_px
    cov = _coverage(_box_sdf(lx, ly, 0, 0, hx, hy), s)
    if board.defect == "broken_edge":
        bx, by, br = board.bite
        cov = cov * (1.0 - _coverage(_disc_sdf(lx, ly, bx, by, br), s))
    yield cov, board.mask_rgb
    # silkscreen marks, a fiducial and a small 0805 part: bright in R, not the target
    for cx, cy, w, h in ((-5.0, -3.5, 2.6, 0.3), (-5.0, 4.0, 0.3, 2.2), (-3.6, 4.0, 1.2, 0.3)):
        yield cov * _coverage(_box_sdf(lx, ly, cx, cy, w / 2, h / 2), s), SILK_RGB
    yield cov * _coverage(_disc_sdf(lx, ly, 5.8, -4.2, 0.5), s), PAD_RGB
    yield cov * _coverage(_box_sdf(lx, ly, -2.0, -3.0, 1.0, 0.625), s), PART_BODY_RGB
    for ex in (-2.8, -1.2):
        yield cov * _coverage(_box_sdf(lx, ly, ex, -3.0, 0.2, 0.625), s), TERMINATION_RGB
    ox, oy = spec.component_offset_mm
    L, W = spec.component_mm
    for ex in (ox - L / 2 + 0.45, ox + L / 2 - 0.45):  # pads under the capacitor's ends
        yield cov * _coverage(_box_sdf(lx, ly, ex, oy, 0.45, 0.8), s), PAD_RGB
    if board.defect != "missing_component":
        yield cov * _coverage(_box_sdf(lx, ly, ox, oy, L / 2, W / 2), s), CAPACITOR_BODY_RGB
        for ex in (ox - L / 2 + 0.3, ox + L / 2 - 0.3):
            yield cov * _coverage(_box_sdf(lx, ly, ex, oy, 0.3, W / 2), s), TERMINATION_RGB


def paint_boards(spec: TraySpec, boards: list[Board], image: np.ndarray) -> None:
    """Paint ``boards`` into ``image`` (H, W, 3) float RGB in place (planar view, no light yet)."""
    height, width = image.shape[:2]
    s = spec.mm_per_px
    reach = np.hypot(*spec.board_mm) / 2 + 2 * s
    for b in boards:
        u0, v0 = tray_to_pixels(spec, [[b.x_mm, b.y_mm]])[0]
        r = reach / s
        ua, ub = max(int(np.floor(u0 - r)), 0), min(int(np.ceil(u0 + r)) + 1, width)
        va, vb = max(int(np.floor(v0 - r)), 0), min(int(np.ceil(v0 + r)) + 1, height)
        if ua >= ub or va >= vb:
            continue
        uu, vv = np.meshgrid(np.arange(ua, ub, dtype=float), np.arange(va, vb, dtype=float))
        xy = pixels_to_tray(spec, np.column_stack([uu.ravel(), vv.ravel()]))
        local = (xy - [b.x_mm, b.y_mm]) @ _rot(np.deg2rad(b.angle_deg))  # Rᵀ (p − c), row-wise
        lx, ly = local[:, 0].reshape(uu.shape), local[:, 1].reshape(uu.shape)
        patch = image[va:vb, ua:ub]
        for cov, rgb in _board_layers(spec, b, lx, ly):
            touched = cov > 0
            patch[touched] += cov[touched][:, None] * (np.asarray(rgb, dtype=float) - patch[touched])


def apply_light(spec: TraySpec, boards: list[Board], image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The ring light and the sensor on a painted planar image (float RGB): exposure, radial fall-off
    (25 % at the corners), glare spots on boards (10–40 DN: a matte solder mask's sheen), dust specks,
    Gaussian noise; uint8 RGB."""
    height, width = image.shape[:2]
    cu, cv = image_centre(spec)
    u = np.arange(width, dtype=np.float32)[None, :]
    v = np.arange(height, dtype=np.float32)[:, None]
    r2 = ((u - cu) ** 2 + (v - cv) ** 2) / (cu ** 2 + cv ** 2)
    out = image.astype(np.float32) * (rng.uniform(0.9, 1.08) * (1.0 - 0.25 * r2))[..., None]
    s = spec.mm_per_px
    for _ in range(spec.glare_spots if boards else 0):
        b = boards[rng.integers(len(boards))]
        gu, gv = tray_to_pixels(spec, [[b.x_mm + rng.uniform(-6, 6), b.y_mm + rng.uniform(-6, 6)]])[0]
        sigma = rng.uniform(0.8, 2.5) / s
        amplitude = rng.uniform(10, 40)
        a, b_ = int(max(gu - 4 * sigma, 0)), int(min(gu + 4 * sigma + 1, width))
        c, d = int(max(gv - 4 * sigma, 0)), int(min(gv + 4 * sigma + 1, height))
        if a < b_ and c < d:
            g = np.exp(-((u[:, a:b_] - gu) ** 2 + (v[c:d] - gv) ** 2) / (2 * sigma ** 2))
            out[c:d, a:b_] += amplitude * g[..., None]
    for _ in range(spec.dust_specks):
        du, dv = rng.uniform(0, width), rng.uniform(0, height)
        radius = rng.uniform(0.03, 0.12) / s
        grey = rng.choice([15.0, 150.0])
        a, b_ = int(max(du - radius - 2, 0)), int(min(du + radius + 3, width))
        c, d = int(max(dv - radius - 2, 0)), int(min(dv + radius + 3, height))
        cov = np.clip(radius + 0.5 - np.hypot(u[:, a:b_] - du, v[c:d] - dv), 0, 1)[..., None]
        out[c:d, a:b_] += cov * (grey - out[c:d, a:b_])
    out += rng.normal(0.0, spec.noise_dn, out.shape).astype(np.float32)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def board_truth(spec: TraySpec, boards: list[Board]) -> pd.DataFrame:
    """One row per board: pocket, pose (mm, deg, tray frame), mask, defect, and its dispensing area
    (the capacitor; NaN when missing): centre (mm, tray frame and planar pixels), long-axis angle in
    [0, 180) deg, length and width (mm)."""
    rows = []
    ox, oy = spec.component_offset_mm
    for b in boards:
        centre = np.array([b.x_mm, b.y_mm]) + _rot(np.deg2rad(b.angle_deg)) @ [ox, oy]
        uv = tray_to_pixels(spec, centre[None])[0]
        has = b.defect != "missing_component"
        rows.append({"board_id": b.board_id, "row": b.row, "col": b.col, "board_x_mm": b.x_mm, "board_y_mm": b.y_mm,
                     "board_angle_deg": b.angle_deg, "mask": b.mask, "defect": b.defect,
                     "area_x_mm": centre[0] if has else np.nan, "area_y_mm": centre[1] if has else np.nan,
                     "area_u_px": uv[0] if has else np.nan, "area_v_px": uv[1] if has else np.nan,
                     "area_angle_deg": b.angle_deg % 180.0 if has else np.nan,
                     "area_length_mm": spec.component_mm[0] if has else np.nan,
                     "area_width_mm": spec.component_mm[1] if has else np.nan})
    return pd.DataFrame(rows)


def paint_tray(spec: TraySpec, boards: list[Board]) -> np.ndarray:
    """The painted planar image (H, W, 3) float RGB of a tray holding ``boards``, before light and noise."""
    width, height = spec.image_px
    image = np.empty((height, width, 3))
    image[:] = TRAY_RGB
    paint_boards(spec, boards, image)
    return image


def render_tray(spec: TraySpec, seed: int, boards: int | None = None, shot: int = 0
                ) -> tuple[np.ndarray, pd.DataFrame, list[Board]]:
    """Render one tray: (uint8 RGB image (H, W, 3), the boards' truth (:func:`board_truth`), the boards).
    ``boards``: how many pockets are filled (all by default; 0: a blank tray). ``seed`` places the
    boards; ``shot`` draws the light and the noise (another shot of the same tray: the repeatability
    of Table 6)."""
    placed = place_boards(spec, np.random.default_rng([seed, 34]), boards)
    image = paint_tray(spec, placed)
    return apply_light(spec, placed, image, np.random.default_rng([seed, 34, shot])), board_truth(spec, placed), placed
