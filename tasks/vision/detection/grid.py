"""Order detected dot centres into the plate's rows × cols grid.

Frames: image px (u right, v down). Plate rows/cols as in :class:`tasks.machine.plate.DotPlate`.

1. *Lattice*: each point links to its nearest neighbours at a spacing consistent with its own
   size (spacing ≈ pitch/diameter × dot diameter in px) and of similar size; the two dominant
   directions of these links (mod 180°) are the lattice axes, whatever the in-plane rotation.
2. *Growth*: from a well-connected seed, integer lattice coordinates spread to neighbours
   predicted one local step away; the local step vectors are carried along, so perspective
   (steps shrinking across the plate) is followed. When no seed reaches the plate's dot count,
   a second round predicts the places a carried step misses from the lattice around them, to
   second order. Points off the lattice (clutter) are never reached.
3. *Window*: the rows × cols (or cols × rows) window of the lattice must be complete and unique,
   and every 2 × 2 cell of it close to a parallelogram (a stray blob that won a dot's claim is
   replaced by the candidate that closes it, :mod:`tasks.vision.detection.lattice_check`);
   otherwise the view is rejected with a reason (out of view, missing dots, extra dots,
   irregular lattice) — unless
   the dots' expected positions are given, when a plate partly out of the image is labelled by
   them (:mod:`tasks.vision.detection.partial_view`) and step 4 is not needed.
4. *Orientation*: of the 8 symmetries of a rectangle, the physical handedness (the camera looks
   at the printed face, plate +Z towards the camera) leaves 4 for a square grid and 2 otherwise
   (a grid of unequal row and column counts, or of unequal row and column pitches: the longer
   spacing in the image must be the plate's longer one).
   The in-plane rotation angle of the plate's +X (column) axis in the image is measured
   counter-clockwise on screen from +u, i.e. ``atan2(−dv, du)`` in degrees; the candidate
   closest to ``expected_rotation_deg`` wins, or the one closest to 0° without a prior (then the
   result is flagged ambiguous).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from tasks.machine.plate import DotPlate
from tasks.vision.detection.grid_order import SIMILAR_SIZE, GridOrder, fail_order, lattice_steps, rotation_deg
from tasks.vision.detection.lattice_check import check_window, extra_dot_limit, plate_like_strays
from tasks.vision.detection.lattice_reason import best_window_fill, incomplete_lattice_reason
from tasks.vision.detection.partial_view import order_by_prior

__all__ = ["GridOrder", "build_lattice", "order_grid", "reduce_lattice"]


def _axis_directions(vec: np.ndarray) -> tuple[float, float] | None:
    """Two dominant directions (rad, mod π) of link vectors (L, 2), or None."""
    phi = np.mod(np.arctan2(vec[:, 1], vec[:, 0]), np.pi)
    nb = 180
    hist = np.bincount((phi / np.pi * nb).astype(int) % nb, minlength=nb).astype(float)
    k = np.exp(-0.5 * (np.arange(-9, 10) / 3.0) ** 2)
    sm = np.convolve(np.concatenate([hist[-9:], hist, hist[:9]]), k, mode="same")[9:-9]
    i1 = int(np.argmax(sm))
    dist = np.abs((np.arange(nb) - i1 + nb / 2) % nb - nb / 2)
    sm2 = np.where(dist < 30, -1.0, sm)
    i2 = int(np.argmax(sm2))
    if sm2[i2] <= 0:
        return None
    return (i1 + 0.5) * np.pi / nb, (i2 + 0.5) * np.pi / nb


def build_lattice(points: np.ndarray, sizes: np.ndarray | None, spacing_ratio: float | tuple[float, float],
                  max_seeds: int = 4, min_points: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Integer lattice coordinates of the points reachable from the best seed.

    points: (N, 2) px; sizes: (N,) dot diameters px (None: use the median link length);
    spacing_ratio: pitch / diameter of the plate, or (smallest, largest) of the row and column
    pitches / diameter for a rectangular lattice. Returns (mn (N, 2) int, assigned (N,) bool);
    among up to ``max_seeds`` seeds the largest lattice wins (stop at one of ``min_points``).
    """
    n = len(points)
    none = (np.zeros((n, 2), int), np.zeros(n, bool))
    if n < 4:
        return none
    tree = cKDTree(points)
    kq = min(9, n)
    dist, idx = tree.query(points, k=kq)
    dist, idx = dist[:, 1:], idx[:, 1:]
    if sizes is not None:
        ratio_lo, ratio_hi = np.broadcast_to(np.asarray(spacing_ratio, dtype=float), (2,))
        lo, hi = 0.5 * ratio_lo * sizes, 1.35 * ratio_hi * sizes  # (N,)
        size_ok = (sizes[idx] < SIMILAR_SIZE * sizes[:, None]) & (sizes[idx] > sizes[:, None] / SIMILAR_SIZE)
    else:
        med = np.median(dist[:, 0])
        lo, hi = np.full(n, 0.6 * med), np.full(n, 1.6 * med)
        size_ok = np.ones_like(dist, dtype=bool)
    link = (dist >= lo[:, None]) & (dist <= hi[:, None]) & size_ok
    if not link.any():
        return none
    src = np.repeat(np.arange(n), kq - 1).reshape(n, kq - 1)
    vec = points[idx[link]] - points[src[link]]
    axes = _axis_directions(vec)
    if axes is None:
        return none
    dirs = np.array([[np.cos(a), np.sin(a)] for a in axes])  # (2, 2)
    # per point: best link along +axis0, -axis0, +axis1, -axis1 (within 25°)
    vall = points[idx] - points[:, None, :]  # (N, k-1, 2)
    lens = np.maximum(np.linalg.norm(vall, axis=2), 1e-9)
    cosang = np.einsum("nkc,dc->nkd", vall, dirs) / lens[..., None]  # (N, k-1, 2)
    c25 = np.cos(np.radians(25))
    steps = np.zeros((n, 4, 2))
    has = np.zeros((n, 4), bool)
    for a in range(2):
        for s, sg in enumerate((1.0, -1.0)):
            m = link & (cosang[..., a] * sg > c25)
            d = np.where(m, dist, np.inf)
            j = np.argmin(d, axis=1)
            h = np.isfinite(d[np.arange(n), j])
            has[:, 2 * a + s] = h
            steps[:, 2 * a + s] = vall[np.arange(n), j]
    full = has.all(axis=1)
    cand = np.flatnonzero(full) if full.any() else np.argsort(-has.sum(axis=1))[:max_seeds]
    if len(cand) == 0:
        return none
    centroid = np.median(points[cand], axis=0)
    cand = cand[np.argsort(np.linalg.norm(points[cand] - centroid, axis=1))][:max_seeds]
    best = none
    # with carried steps first; only when no seed reaches ``min_points``, again with the places a
    # carried step misses predicted from the lattice (it can also reach strays beyond the plate)
    for second_order in (False, True):
        if second_order and (min_points == 0 or best[1].sum() >= min_points):
            break
        for seed in cand:
            mn, assigned = _grow(points, tree, int(seed), steps, has, sizes, second_order)
            if assigned.sum() > best[1].sum():
                best = (mn, assigned)
            if assigned.sum() >= min_points:
                break
    return best


def _grow(points, tree, seed, steps, has, sizes, second_order: bool = False):
    """Breadth-first assignment of lattice coordinates from ``seed``, one frontier at a time.

    Every frontier point predicts its 4 neighbours one local step away (one batched KD-tree
    query per frontier); a point within 30 % of a step of a prediction joins the lattice (first
    claim wins) and inherits the local steps, updated along the direction it was reached by (and
    its opposite). The four directions keep their own steps: under strong lens distortion the
    step to one side of a dot can be half as long again as the step to the other. With
    ``second_order``, where the carried step finds no point the place is predicted from the lattice
    around it instead, to second order where three places behind it are filled
    (:func:`_second_order_steps`: perspective and a fisheye change the step from one dot to the next
    by a third and more, beyond the 30 % a carried step allows), and when the frontier is empty
    every point is expanded once more, with the lattice then known around it.
    """
    n = len(points)
    mn = np.zeros((n, 2), int)
    assigned = np.zeros(n, bool)
    b = np.zeros((n, 4, 2))  # local step vectors along +axis0, -axis0, +axis1, -axis1 (uv)
    for k in range(4):
        opposite = k ^ 1
        b[seed, k] = steps[seed, k] if has[seed, k] else -steps[seed, opposite]
    assigned[seed] = True
    frontier = np.array([seed])
    axis_of = np.array([0, 0, 1, 1])
    sign_of = np.array([1.0, -1.0, 1.0, -1.0])
    at = {(0, 0): seed}  # lattice coordinates → point
    revisit = True
    while len(frontier):
        f = np.repeat(frontier, 4)  # (F*4,)
        k = np.tile(np.arange(4), len(frontier))
        step = b[f, k]  # (F*4, 2)

        def claims(step, f=f):
            d, j = tree.query(points[f] + step)
            ok = np.isfinite(d) & (d <= 0.3 * np.linalg.norm(step, axis=1))
            j = np.where(ok, j, 0)
            if sizes is not None:
                ok &= (sizes[j] > sizes[f] / SIMILAR_SIZE) & (sizes[j] < sizes[f] * SIMILAR_SIZE)
            return ok & ~assigned[j], j

        ok, j = claims(step)
        if second_order and not ok.all():  # where the carried step finds nothing: predicted from the lattice
            miss = np.flatnonzero(~ok)
            ahead = _second_order_steps(points, mn, at, f[miss], axis_of[k[miss]], sign_of[k[miss]].astype(int),
                                        step[miss])
            ok2, j2 = claims(ahead, f[miss])
            ok[miss[ok2]], j[miss[ok2]] = True, j2[ok2]
        sel = np.flatnonzero(ok)
        _, first = np.unique(j[sel], return_index=True)
        sel = sel[first]
        jj, ff, kk = j[sel], f[sel], k[sel]
        assigned[jj] = True
        mn[jj] = mn[ff]
        mn[jj, axis_of[kk]] += sign_of[kk].astype(int)
        b[jj] = b[ff]
        taken = points[jj] - points[ff]
        b[jj, kk] = taken
        b[jj, kk ^ 1] = -taken
        at.update({(int(a), int(c)): int(j) for (a, c), j in zip(mn[jj], jj, strict=True)})
        frontier = jj
        if not len(frontier) and second_order and revisit and assigned.sum() > 1:
            # once: every point again, now that the places behind it are known (a point expanded
            # before them had only the carried step)
            frontier, revisit = np.flatnonzero(assigned), False
    return mn, assigned


def _second_order_steps(points, mn, at, f, axis, sign, step):
    """Steps (M, 2) px from points ``f`` (M,) one lattice place along ``axis`` (M,) in direction
    ``sign`` (M,), predicted from the lattice found so far (``at``: lattice coordinates → point):
    the target place t is extrapolated to second order along a direction d through it where the
    three places behind it are filled, p(t−d) + Δ + (Δ − Δ'), Δ = p(t−d) − p(t−2d),
    Δ' = p(t−2d) − p(t−3d), when |Δ + Δ − Δ'| is within ×⅔…×1.5 of |Δ| (the direction of growth
    first, then the others); where no direction gives that, Δ turned and scaled as Δ' → Δ
    (:func:`_similar_step`); elsewhere ``step`` as given (the carried step)."""
    out = step.copy()
    dirs = ((1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (-1, -1), (1, -1), (-1, 1))
    for i in range(len(f)):
        e = [0, 0]
        e[axis[i]] = sign[i]
        t = (int(mn[f[i], 0]) + e[0], int(mn[f[i], 1]) + e[1])
        lines = []  # (p(t−d), Δ, Δ') along every direction d with the three places behind t filled
        for d in sorted(dirs, key=lambda d: d != tuple(e)):  # the direction of growth first
            behind = [at.get((t[0] - j * d[0], t[1] - j * d[1])) for j in (1, 2, 3)]
            if all(b is not None for b in behind):
                p1, p2, p3 = (points[b] for b in behind)
                lines.append((p1, p1 - p2, p2 - p3))
        for p1, delta, before in lines:
            ahead = 2.0 * delta - before
            if 2.0 / 3.0 < np.linalg.norm(ahead) / max(float(np.linalg.norm(delta)), 1e-9) < 1.5:
                out[i] = p1 + ahead - points[f[i]]
                break
        else:
            for p1, delta, before in lines:
                ahead = _similar_step(delta, before)
                if ahead is not None:
                    out[i] = p1 + ahead - points[f[i]]
                    break
    return out


def _similar_step(delta: np.ndarray, before: np.ndarray) -> np.ndarray | None:
    """The step after ``delta`` (2,) px when each step is the one before it turned and scaled alike
    (``before`` → ``delta``), or None when that scale is outside ×½…×2: where the steps shrink by a
    third and more per dot (near the rim of a fisheye) the second difference overshoots, and a
    geometric sequence follows them."""
    d, b = complex(*delta), complex(*before)
    if abs(b) < 1e-9 or not 0.5 < abs(d / b) < 2.0:
        return None
    z = d * (d / b)
    return np.array([z.real, z.imag])


def _unimodular(limit: int = 2) -> np.ndarray:
    """(M, 2, 2) integer matrices with entries in [−limit, limit] and determinant ±1."""
    v = np.arange(-limit, limit + 1)
    a, b, c, d = (x.ravel() for x in np.meshgrid(v, v, v, v, indexing="ij"))
    keep = np.abs(a * d - b * c) == 1
    return np.stack([a[keep], b[keep], c[keep], d[keep]], axis=1).reshape(-1, 2, 2)


_UNIMODULAR = _unimodular()


def reduce_lattice(mn: np.ndarray) -> np.ndarray:
    """Re-express integer lattice coordinates (N, 2) in the basis whose bounding box is smallest.

    Growth may follow a diagonal of the plate as a lattice axis (under strong foreshortening a
    diagonal can be as short as a row step); any such basis spans the same lattice, and the one
    in which the dots fill the tightest box is the plate's rows and columns.
    """
    t = np.einsum("mij,nj->mni", _UNIMODULAR, mn)  # (M, N, 2)
    ext = t.max(axis=1) - t.min(axis=1) + 1  # (M, 2)
    area = ext[:, 0] * ext[:, 1]
    best = int(np.argmin(area * 4 + (np.abs(_UNIMODULAR).sum(axis=(1, 2)) > 2)))
    return t[best]


def _dihedral(rows: int, cols: int, h: int, w: int):
    """Maps (a, b) in an h × w window → (row, col) in rows × cols: list of (2×2 matrix, offset)."""
    out = []
    for perm in ((0, 1), (1, 0)):
        for sa in (1, -1):
            for sb in (1, -1):
                m = np.zeros((2, 2), int)
                m[0, perm[0]] = sa
                m[1, perm[1]] = sb
                dims = np.array([h, w])[list(perm)]
                if dims[0] != rows or dims[1] != cols:
                    continue
                off = np.array([0 if sa > 0 else rows - 1, 0 if sb > 0 else cols - 1])
                out.append((m, off))
    return out


def order_grid(points: np.ndarray, plate: DotPlate, *, sizes: np.ndarray | None = None,
               image_shape: tuple[int, int] | None = None, expected_rotation_deg: float | None = None,
               mirrored: bool = False, lattice: tuple[np.ndarray, np.ndarray] | None = None,
               expected_centres: np.ndarray | None = None, levels: np.ndarray | None = None) -> GridOrder:
    """Assign detected points (N, 2) px to the plate's dots.

    sizes: (N,) dot diameters in px (major axis), used to bound neighbour spacing and reject
    clutter of another size; image_shape (H, W) lets the reason say when the plate leaves the
    image; mirrored flips the expected handedness (a plate seen from its back); ``lattice``
    supplies precomputed integer coordinates (mn (N, 2), assigned (N,)) and skips steps 1–2.
    expected_centres: (rows*cols, 2) px, where the dots should be (same frame as ``points``); with
    ``image_shape``, a lattice without a complete window is then ordered as a partial view
    (:func:`tasks.vision.detection.partial_view.order_by_prior`: ``index`` is −1 for the dots not found).
    levels: (N, 2) grey inside each point's dot and on the ring around it; with ``sizes``, the
    lattice points beyond a complete window that do not continue the window's lattice, size and
    levels are clutter and do not count as extra dots (:func:`tasks.vision.detection.lattice_check.plate_like_strays`).
    """
    rows, cols = plate.rows, plate.cols
    need = rows * cols
    points = np.asarray(points, dtype=float)
    if len(points) == 0:
        return fail_order(plate, "no dot candidates found")
    mn, assigned = lattice if lattice is not None else build_lattice(
        points, sizes, tuple(p / plate.dot_diameter_mm for p in plate.pitch_range_mm), min_points=need)
    sel = np.flatnonzero(assigned)
    if len(sel) < 4:
        return fail_order(plate, f"no dot lattice found among {len(points)} candidates (expected {rows}x{cols})")
    g = reduce_lattice(mn[sel])
    g = g - g.min(axis=0)
    hh, ww = (g.max(axis=0) + 1).tolist()
    occ = np.full((hh, ww), -1)
    occ[g[:, 0], g[:, 1]] = sel
    filled = (occ >= 0).astype(int)
    cum = np.pad(filled.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    shapes = {(rows, cols), (cols, rows)}
    windows = []
    for h, w in shapes:
        if h > hh or w > ww:
            continue
        s = cum[h:, w:] - cum[:-h, w:] - cum[h:, :-w] + cum[:-h, :-w]  # (hh-h+1, ww-w+1)
        for a0, b0 in zip(*np.nonzero(s == need), strict=True):
            windows.append((h, w, int(a0), int(b0)))
    shape_txt = f"{hh}x{ww}"
    if not windows and expected_centres is not None and image_shape is not None:
        return order_by_prior(points, sel, g, plate, np.asarray(expected_centres, dtype=float), image_shape)
    if not windows:
        fill = best_window_fill(points[sel], g, rows, cols, image_shape)
        refusal = fail_order(plate, incomplete_lattice_reason(fill, shape_txt, len(sel), rows, cols), (hh, ww),
                             (sel, g), window_dots=fill.count)
        if lattice is not None:
            return refusal
        return order_beside(refusal, points, sel, plate, sizes=sizes, levels=levels, image_shape=image_shape,
                            expected_rotation_deg=expected_rotation_deg, mirrored=mirrored)
    if len(windows) > 1:
        return fail_order(plate, f"extra dots: {shape_txt} lattice holds {len(windows)} complete "
                                 f"{rows}x{cols} windows; which one is the plate is ambiguous", (hh, ww), (sel, g),
                          window_dots=need, complete_windows=len(windows))
    h, w, a0, b0 = windows[0]
    strays = len(sel) - need
    limit = extra_dot_limit(rows, cols)
    if strays >= limit and levels is not None and sizes is not None:
        like = plate_like_strays(points, sizes, levels, occ, windows[0]).sum()
        strays = strays if like >= limit else 0
    if strays >= limit:
        return fail_order(plate, f"extra dots: {strays} lattice-aligned dots beyond the {rows}x{cols} "
                                 f"window ({shape_txt} lattice)", (hh, ww), (sel, g), window_dots=need)
    win, irregular = check_window(points, sizes, occ[a0 : a0 + h, b0 : b0 + w])
    if irregular:
        return fail_order(plate, irregular, (hh, ww), (sel, g), window_dots=need)
    ab = np.stack(np.meshgrid(np.arange(h), np.arange(w), indexing="ij"), axis=-1).reshape(-1, 2)
    pidx = win.reshape(-1)
    pts = points[pidx]
    cands = []
    for m, off in _dihedral(rows, cols, h, w):
        rc = ab @ m.T + off  # (need, 2) row, col
        dcol, drow = lattice_steps(pts, rc)
        cross = dcol[0] * drow[1] - dcol[1] * drow[0]
        if (cross < 0) == mirrored:
            continue
        if not plate.is_square_lattice and (np.hypot(*dcol) > np.hypot(*drow)) != (plate.pitch_mm > plate.pitch_y_mm):
            continue  # a quarter turn would swap the plate's long and short spacings
        ang = float(rotation_deg(dcol))
        cands.append((ang, rc))
    if not cands:
        return fail_order(plate, "internal: no orientation with the expected handedness")
    ref = 0.0 if expected_rotation_deg is None else float(expected_rotation_deg)
    diffs = np.array([abs((a - ref + 180.0) % 360.0 - 180.0) for a, _ in cands])
    order = np.argsort(diffs)
    ang, rc = cands[order[0]]
    if expected_rotation_deg is None:
        ambiguous = len(cands) > 1
    else:
        ambiguous = len(cands) > 1 and diffs[order[1]] - diffs[order[0]] < 20.0
    index = np.full(need, -1)
    index[rc[:, 0] * cols + rc[:, 1]] = pidx
    return GridOrder(True, "", index, ang, ambiguous, (hh, ww), window_dots=need)


def order_beside(refusal: GridOrder, points: np.ndarray, used: np.ndarray, plate: DotPlate, *,
                 sizes: np.ndarray | None, levels: np.ndarray | None, **kw) -> GridOrder:
    """The ordering of the points (N, 2) px outside the lattice ``used`` (indices) that ``refusal``
    holds, when it finds the grid or fills more of one rows × cols window; else ``refusal``.

    Growth keeps the largest lattice of its seeds: a larger lattice of clutter beside the plate (a
    line of lettering of the dots' size) wins, and the plate's dots, left out of it, were never
    ordered. ``kw``: :func:`order_grid`'s ``image_shape``, ``expected_rotation_deg``, ``mirrored``.
    """
    rest = np.setdiff1d(np.arange(len(points)), used)
    if len(rest) < 4 or len(rest) <= refusal.window_dots:
        return refusal
    sub_sizes = None if sizes is None else sizes[rest]
    lattice = build_lattice(points[rest], sub_sizes, tuple(p / plate.dot_diameter_mm for p in plate.pitch_range_mm),
                            min_points=plate.rows * plate.cols)
    other = order_grid(points[rest], plate, sizes=sub_sizes, levels=None if levels is None else levels[rest],
                       lattice=lattice, **kw)
    if not (other.ok or other.window_dots > refusal.window_dots):
        return refusal
    return replace(other, index=np.where(other.index >= 0, rest[np.maximum(other.index, 0)], -1),
                   lattice_index=None if other.lattice_index is None else rest[other.lattice_index])
