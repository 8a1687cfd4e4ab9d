"""The RRHT-based dot-grid detection framework (seed paper §4.1, adapted to dot grids and photographs).

    image ─ downsample ─ median + gamma ─ Canny ─ chain-code filter ─ RRHT circles (coarse)
          ─ appearance test ─ grid ordering  (no grid: + region-contour candidates, order again)
          ─ sub-pixel ellipses in circular ROIs at full size (RANSAC + LSQ, pixel edge fit)
          ─ homography + perspective-bias correction (local homographies under lens distortion)
          ─ GridDetection

Without a scale hint the coarse search runs over bands of dot size until one yields the grid
(:func:`search_bands`): dots of 1/128–1/14 of the image's longer side (every campaign view), then
1/28–1/3.5 on a 4× coarser image (a grid filling a photograph), then, on large images, 12 px up
at half and 6–16 px at full resolution (the latter's Hough grid taken before the former's region
contours when its dots are below the former's, :func:`small_dot_grid`); a band whose 1–99 % grey
stretch would clip a small tail (a few dots on a large even page) is searched again stretched to
the far tails. Candidates must
look like a filled dot on a clear ring of plate
(:mod:`tasks.vision.detection.verify`); when the Hough circles give no grid, dark (light) regions
against their local mean are added (:mod:`tasks.vision.detection.blobs`). When every band refuses,
two neighbouring bands' candidates are ordered together, then the most plate-like band's lattice
(:meth:`CoarseAttempt.plate_likeness`) is looked at again where its best window lacks one or two
dots inside the image (:mod:`tasks.vision.detection.completion`), and failing that its band is searched
again on a log scale (:func:`on_log_scale`: a cast shadow's edge across dark dots); before that, for dots
blurred as wide as the gap between them, each band's candidates with its faint regions and their sizes
scaled for the blur's shrinking (:func:`shrunk_by_blur`). A dot whose rim fit fails is fitted again from a
well-fitted neighbour's ellipse (:func:`refit_from_neighbours`). A view without exactly one
complete rows × cols window is refused with the reason (:mod:`tasks.vision.detection.grid`,
:mod:`tasks.vision.detection.lattice_reason`), the most plate-like band's: a wrong labelling is
worse than none.

SYNOPSIS

    >>> from tasks.vision.detection.framework import detect_rrht
    >>> det = detect_rrht(image, plate, px_per_mm_hint=60.0)   # doctest: +SKIP
    >>> det.ok, det.centres.shape                                # (True, (49, 2))  # doctest: +SKIP

Units: px of the input image unless a name says otherwise; frames as in :mod:`tasks.vision.detection.result`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from itertools import pairwise

import numpy as np

from tasks.machine.plate import DotPlate
from tasks.vision.detection.beyond_window import continued_beyond
from tasks.vision.detection.blobs import contour_candidates
from tasks.vision.detection.chaincode import filter_edges
from tasks.vision.detection.completion import missed_dots
from tasks.vision.detection.edges import canny_edges
from tasks.vision.detection.grid import order_grid
from tasks.vision.detection.grid_order import SIMILAR_SIZE, GridOrder
from tasks.vision.detection.partial_view import too_few_dots
from tasks.vision.detection.perspective import corrected_centres, fit_homography
from tasks.vision.detection.preprocess import (
    auto_gamma,
    check_image,
    coarse_to_full,
    downsample,
    full_to_coarse,
    log_stretch,
)
from tasks.vision.detection.result import GridDetection
from tasks.vision.detection.rrht import CoarseCircles, RRHTParams, rrht_circles
from tasks.vision.detection.subpixel import EllipseFits, SubpixelParams, refine_ellipses, rim_reach_px
from tasks.vision.detection.verify import dot_appearance


@dataclass
class FrameworkParams:
    coarse_target_diameter_px: float = 12.0  # dot diameter aimed at on the coarse image
    coarse_width_px: int = 768  # without a scale hint: coarse image about this wide
    median_ksize: int = 3
    min_support: float = 0.5  # per-dot fraction of the rim that must give inlier points
    contour_fallback: bool = True  # add region-contour candidates when the Hough circles give no grid
    min_fill_inside: float = 0.9  # a candidate's disc must look like a dot … (tasks.vision.detection.verify)
    min_fill_outside: float = 0.85  # … on a clear ring of plate
    bias_iterations: int = 2
    distorted_misfit_px: float = 0.15  # RMS misfit (px) of the plate homography, well above centre noise,
    # beyond which lens distortion dominates and the bias is computed from local homographies
    seed: int = 0
    rrht: RRHTParams = field(default_factory=RRHTParams)
    subpixel: SubpixelParams = field(default_factory=SubpixelParams)


def cut_by_border(centres_px: np.ndarray, major_semi_axes_px: np.ndarray, gap_ratio: float,
                  image_shape: tuple[int, int]) -> np.ndarray:
    """(K,) bool: dots (centres (K, 2) px, major semi-axes (K,) px) whose rim rays
    (:func:`tasks.vision.detection.subpixel.rim_reach_px`), plus 2 px, would leave an image of
    ``image_shape`` (H, W): the border cuts what their rim fit needs."""
    h, w = image_shape
    reach = rim_reach_px(major_semi_axes_px, gap_ratio) + 2.0
    u, v = centres_px[:, 0], centres_px[:, 1]
    return (u < reach) | (u > w - 1 - reach) | (v < reach) | (v > h - 1 - reach)


def search_scale(shape: tuple[int, int], plate: DotPlate, px_per_mm_hint: float | None,
                 target_d: float, coarse_width: int) -> tuple[int, float, float]:
    """(downsampling factor, min and max dot diameter in full-size px) for the first coarse search.

    With a hint the diameter is known to within perspective foreshortening and focus changes
    (×0.55…1.5); without one, dots from 1/128 to 1/14 of the longer image side are searched.
    """
    big = max(shape)
    if px_per_mm_hint is not None and px_per_mm_hint > 0:
        d = px_per_mm_hint * plate.dot_diameter_mm
        factor = int(np.clip(np.floor(d / target_d), 1, 8))
        return factor, 0.55 * d, 1.5 * d
    factor = max(1, round(big / coarse_width))
    return factor, big / 128.0, big / 14.0


LARGE_DOT_BAND = (28.0, 3.5)
"""Second search without a scale hint: dots from 1/28 to 1/3.5 of the longer image side (a
grid that fills a phone photograph or a webcam frame), on an image downsampled so that they
are again 6 to 50 coarse px across; it overlaps the first band by a factor 2."""
SMALL_DOT_PX = 6.0
"""Last searches, on a large image whose first band starts above 8 px (a distant plate in a phone
photograph): dots from 12 px to twice the first band's smallest at half resolution, then from
6 to 16 px at full resolution."""


def search_bands(shape: tuple[int, int], plate: DotPlate, px_per_mm_hint: float | None, target_d: float,
                 coarse_width: int) -> list[tuple[int, float, float]]:
    """The coarse searches to try in turn: (factor, d_min, d_max) px, see :func:`search_scale`.

    Without a hint the first band covers dots of 1/128 to 1/14 of the longer side; when it finds
    no grid, :data:`LARGE_DOT_BAND` is searched on a 4× coarser image, then (on images whose
    first band starts above 8 px) the small dots of :data:`SMALL_DOT_PX`.
    """
    first = search_scale(shape, plate, px_per_mm_hint, target_d, coarse_width)
    if px_per_mm_hint is not None and px_per_mm_hint > 0:
        return [first]
    big = max(shape)
    lo, hi = LARGE_DOT_BAND
    bands = [first, (max(1, round(big / (coarse_width / 4))), big / lo, big / hi)]
    if first[1] > 8.0:  # small dots: at half resolution down to 12 px, then at full resolution
        bands += [(2, 2 * SMALL_DOT_PX, 2.0 * first[1]), (1, SMALL_DOT_PX, 2.7 * SMALL_DOT_PX)]
    return bands


@dataclass
class CoarseAttempt:
    """One coarse search: circles on the coarse image, their ordering (None: too few circles)."""

    factor: int
    circles: CoarseCircles
    order: GridOrder | None
    reason: str
    levels: np.ndarray | None = None  # (K, 2) grey inside each circle and on the ring around it
    shape: tuple[int, int] = (0, 0)  # of the coarse image
    image: np.ndarray | None = None  # the preprocessed coarse image searched

    @property
    def ok(self) -> bool:
        return self.order is not None and self.order.ok

    @property
    def score(self) -> int:
        """How far the search got: lattice size found (for choosing which failure to report)."""
        if self.order is None:
            return -1
        return int(np.prod(self.order.lattice_shape))

    @property
    def holds_bigger_grid(self) -> bool:
        """The lattice holds two complete windows of the plate or more (:attr:`GridOrder.bigger_grid`): the
        dots of a larger grid, refused as "extra dots"; neither fainter candidates, nor their sizes scaled
        for blur, nor a place looked at again, nor a search on a log scale (on which dots stay dots)
        removes a dot, so those searches are not made for it."""
        return self.order is not None and self.order.bigger_grid

    def plate_likeness(self, plate: DotPlate) -> tuple[int, float, int]:
        """How likely this band's lattice is the plate's, for choosing which refusal to report when
        every band refuses: the most of its points in one window of the plate's shape, then how near
        its spacing over its dots' size is to the plate's pitch over diameter (minus the absolute log
        ratio), then its size (:attr:`score`). A lattice of clutter on a busy background can be
        larger than the plate's, but rarely fills as much of a rows × cols window at the plate's
        proportions."""
        if self.order is None or self.order.lattice_index is None or len(self.order.lattice_index) < 2:
            return (-1, -np.inf, self.score)
        idx = self.order.lattice_index
        c = self.circles.centres[idx]
        d = np.linalg.norm(c[:, None, :] - c[None, :, :], axis=2)
        np.fill_diagonal(d, np.inf)
        ratio = float(np.median(d.min(axis=1) / (2.0 * self.circles.axes[idx, 0])))
        want = plate.pitch_range_mm[0] / plate.dot_diameter_mm
        return (self.order.window_dots, -abs(float(np.log(ratio / want))), self.score)

    def spacing_over_size(self) -> float:
        """Median over the grid's dots of the distance to the nearest other dot of the grid over
        the dot's diameter (major axis); NaN without a grid."""
        if not self.ok:
            return float("nan")
        idx = self.order.index[self.order.index >= 0]
        c = self.circles.centres[idx]
        d = np.linalg.norm(c[:, None, :] - c[None, :, :], axis=2)
        np.fill_diagonal(d, np.inf)
        return float(np.median(d.min(axis=1) / (2.0 * self.circles.axes[idx, 0])))

    def candidates_full(self) -> tuple[np.ndarray, np.ndarray]:
        """(centres (K, 2), diameters (K,)) of the circles found, full-size px."""
        return coarse_to_full(self.circles.centres, self.factor), 2.0 * self.circles.axes[:, 0] * self.factor


class BandSearch:
    """One band's coarse search: downsample ``image`` by ``factor``, find circles of d_min…d_max
    full-size px with the RRHT and order them into the plate's grid (all on the coarse image;
    timings add up in ``tm``, ``kw`` are :func:`ordered_attempt`'s keywords). In two steps:
    :meth:`hough`, the Hough circles alone on each grey stretch (cheap), then :meth:`full`, with the
    region-contour fallback where the circles give no grid, continued from the first step's attempts
    (not searched again)."""

    def __init__(self, image: np.ndarray, plate: DotPlate, factor: int, d_min: float, d_max: float,
                 p: FrameworkParams, tm: dict, kw: dict):
        self.image, self.plate, self.factor, self.d_min, self.d_max = image, plate, factor, d_min, d_max
        self.p, self.tm, self.kw = p, tm, kw
        self._hough: list[CoarseAttempt] = []
        self._n_stretches: int | None = None  # known once the first stretch is searched
        self._small: np.ndarray | None = None
        self._means: list[tuple[np.ndarray, dict]] = []  # (stretch image, its local means' store)

    def means(self, pre: np.ndarray) -> dict | None:
        """The store of local means of ``pre`` (one of the band's stretched images) for its region
        searches at every offset (:func:`tasks.vision.detection.blobs.contour_candidates`' ``means``);
        None for a band the blur fallback does not search again (:data:`BLUR_BAND_DOT_PX`): its means
        are freed window by window."""
        if self.d_min > BLUR_BAND_DOT_PX:
            return None
        for image, store in self._means:
            if image is pre:
                return store
        self._means.append((pre, {}))
        return self._means[-1][1]

    def release_means(self) -> None:
        """Free the stores of :meth:`means` (at 12 MP up to four float32 images, about 190 MB)."""
        self._means.clear()

    def small(self) -> np.ndarray:
        """The image downsampled by the band's factor (made once; its preprocessing is timed by the caller)."""
        if self._small is None:
            self._small = downsample(self.image, self.factor)
        return self._small

    def _next_stretch(self) -> None:
        """Search the band's next grey stretch (the first: 1–99 %; the second, where
        :func:`tasks.vision.detection.preprocess.keep_small_tails` says the far tails differ: to them)."""
        t0 = time.perf_counter()
        small_tails = self._n_stretches is not None
        pre, stretch = auto_gamma(self.small(), self.p.median_ksize, small_tails=small_tails)
        if self._n_stretches is None:
            self._n_stretches = 2 if stretch["tails_differ"] else 1
        self.tm["preprocess"] = self.tm.get("preprocess", 0.0) + time.perf_counter() - t0
        self._hough.append(hough_attempt(pre, self.plate, self.factor, self.d_min, self.d_max, self.p, self.tm,
                                         **self.kw))

    def hough(self) -> list[CoarseAttempt]:
        """The band's attempts from the Hough circles alone: one per grey stretch (a second where
        :func:`tasks.vision.detection.preprocess.keep_small_tails` says the far tails differ: a few dots
        on a large even page lie beyond the 1–99 % stretch, clipped, and a faint halo round them can give
        the edges)."""
        while self._n_stretches is None or len(self._hough) < self._n_stretches:
            self._next_stretch()
        return self._hough

    def hough_is_final(self) -> bool:
        """True when :meth:`full` would return the Hough circles' grid: every stretch found it, so no
        region contours are added. A stretch is searched only while the ones before it found the grid
        (each stretch's search is its own, so the answer and the later attempts do not change)."""
        while all(a.ok for a in self._hough) and (self._n_stretches is None or len(self._hough) < self._n_stretches):
            self._next_stretch()
        return all(a.ok for a in self._hough)

    def full(self) -> CoarseAttempt:
        """The band's result: each stretch's attempt with region contours where its circles give no
        grid; of two grids found, the one whose spacing over its dots' size is nearer the plate's."""
        done = [a if a.ok or not self.p.contour_fallback else
                with_regions(a, self.plate, self.d_min, self.d_max, self.p, self.tm, self.means(a.image), **self.kw)
                for a in self.hough()]
        if len(done) == 1:
            return done[0]
        attempt, retry = done
        if attempt.ok and retry.ok:
            want = np.log(self.plate.pitch_range_mm[0] / self.plate.dot_diameter_mm)
            return min((attempt, retry), key=lambda a: abs(np.log(a.spacing_over_size()) - want))
        return retry if retry.ok or retry.score > attempt.score else attempt


def ordered_attempt(pre: np.ndarray, c: CoarseCircles, levels: np.ndarray, plate: DotPlate, factor: int, tm: dict, *,
                    expected_rotation_deg: float | None, mirrored: bool, expected_centres_px: np.ndarray | None
                    ) -> CoarseAttempt:
    """The attempt of ordering the candidates ``c`` (coarse px on ``pre``, grey levels (K, 2)) into the grid."""
    if len(c) < 4:
        return CoarseAttempt(factor, c, None, f"found {len(c)} dot-like targets, not a {plate.rows}x{plate.cols} "
                                              "dot grid", levels, pre.shape, pre)
    prior = None if expected_centres_px is None else full_to_coarse(expected_centres_px, factor)
    t3 = time.perf_counter()
    order = order_grid(c.centres, plate, sizes=2 * c.axes[:, 0], image_shape=pre.shape,
                       expected_rotation_deg=expected_rotation_deg, mirrored=mirrored, expected_centres=prior,
                       levels=levels)
    tm["ordering"] = tm.get("ordering", 0.0) + time.perf_counter() - t3
    return CoarseAttempt(factor, c, order, order.reason, levels, pre.shape, pre)


def verified(pre: np.ndarray, c: CoarseCircles, dark_dots: bool, p: FrameworkParams
             ) -> tuple[CoarseCircles, np.ndarray]:
    """The candidates of ``c`` that look like a dot on ``pre`` (:mod:`tasks.vision.detection.verify`)
    and their grey levels (K, 2)."""
    fill_in, fill_out, levels = dot_appearance(pre, c.centres, c.axes, c.theta, dark_dots)
    keep = (fill_in >= p.min_fill_inside) & (fill_out >= p.min_fill_outside)
    return c.subset(keep), levels[keep]


def hough_attempt(pre: np.ndarray, plate: DotPlate, factor: int, d_min: float, d_max: float, p: FrameworkParams,
                  tm: dict, **kw) -> CoarseAttempt:
    """The RRHT circles of d_min…d_max full-size px on the preprocessed coarse image ``pre``
    (downsampled by ``factor``) that look like dots, ordered into the plate's grid."""
    t1 = time.perf_counter()
    em = canny_edges(pre)
    edges, _ = filter_edges(em.edges, d_min / factor, d_max / factor)
    tm["edges"] = tm.get("edges", 0.0) + time.perf_counter() - t1
    circles = CoarseCircles.empty()
    if edges.any():
        circles = rrht_circles(em, edges, plate.dark_dots, d_min / factor / 2, d_max / factor / 2, p.rrht,
                               seed=p.seed, timings=tm)
    circles, levels = verified(pre, circles, plate.dark_dots, p)
    return ordered_attempt(pre, circles, levels, plate, factor, tm, **kw)


def with_regions(attempt: CoarseAttempt, plate: DotPlate, d_min: float, d_max: float, p: FrameworkParams, tm: dict,
                 means: dict | None = None, **kw) -> CoarseAttempt:
    """``attempt`` (the Hough circles' of a band, which give no grid) with the dark (light) regions of
    d_min…d_max full-size px of its coarse image added (:mod:`tasks.vision.detection.blobs`; ``means``:
    the image's store of local means, :meth:`BandSearch.means`)."""
    pre, factor, circles, levels = attempt.image, attempt.factor, attempt.circles, attempt.levels
    t4 = time.perf_counter()
    regions = contour_candidates(pre, plate.dark_dots, d_min / factor, d_max / factor, means=means)
    blobs, blob_levels = verified(pre, regions, plate.dark_dots, p)
    merged, added = merge_candidates(circles, blobs)
    tm["contours"] = tm.get("contours", 0.0) + time.perf_counter() - t4
    if len(merged) == len(circles):
        return attempt
    retry = ordered_attempt(pre, merged, np.concatenate([levels, blob_levels[added]]), plate, factor, tm, **kw)
    # of two refusals the more plate-like lattice is kept (looking again and the reason work on it): a
    # larger lattice of clutter (lettering beside the plate) can hold fewer of a window's dots
    best = retry if retry.ok or retry.plate_likeness(plate) >= attempt.plate_likeness(plate) else attempt
    if best.ok:
        return best
    # under a strong blur the Hough circle can lock on to a ring inside a dot, of another size than
    # the dot's region: with those regions too, the lattice takes the one that fits its neighbours
    more, also = merge_candidates(merged, blobs.subset(~added), other_sizes=True)
    if not also.any():
        return best
    last = ordered_attempt(pre, more, np.concatenate([levels, blob_levels[added], blob_levels[~added][also]]), plate,
                           factor, tm, **kw)
    return last if last.ok or last.plate_likeness(plate) >= best.plate_likeness(plate) else best


def join_bands(attempts: list[CoarseAttempt], plate: DotPlate, tm: dict, *, expected_rotation_deg: float | None,
               mirrored: bool) -> CoarseAttempt | None:
    """The grid from the candidates of two neighbouring bands together (by downsampling factor), on
    the finer band's coarse image, or None when no pair gives it.

    Through a fisheye or under a strong tilt the dots of one plate can span more than a band: the
    large dots near the lens's axis beyond one band's largest, the squeezed ones at the rim found
    only by the finer band (a circle of the coarser band at the place of one of the finer, of a
    similar size, is the same candidate)."""
    done = sorted((a for a in attempts if len(a.circles) and a.levels is not None), key=lambda a: a.factor)
    for finer, coarser in pairwise(done):
        if finer.factor == coarser.factor:
            continue
        scale = coarser.factor / finer.factor
        c = coarser.circles
        moved = CoarseCircles(full_to_coarse(coarse_to_full(c.centres, coarser.factor), finer.factor), c.axes * scale,
                              c.theta, c.votes, c.rim_ratio)
        merged, added = merge_candidates(finer.circles, moved)
        if not added.any():
            continue
        joined = ordered_attempt(finer.image, merged, np.concatenate([finer.levels, coarser.levels[added]]), plate,
                                 finer.factor, tm, expected_rotation_deg=expected_rotation_deg, mirrored=mirrored,
                                 expected_centres_px=None)
        if joined.ok:
            return joined
    return None


def complete_window(attempt: CoarseAttempt, plate: DotPlate, p: FrameworkParams, tm: dict, *,
                    expected_rotation_deg: float | None, mirrored: bool) -> CoarseAttempt | None:
    """The grid from ``attempt``'s candidates and the dots found by looking again at the places its
    best window lacks (:mod:`tasks.vision.detection.completion`), each passing the candidates' test
    of the disc (at least ``min_fill_inside`` on the dot's side of the halfway grey); None when none
    is found or the lattice still refuses."""
    order = attempt.order
    if attempt.image is None or attempt.levels is None or order is None or order.lattice_index is None:
        return None
    t0 = time.perf_counter()
    extra = missed_dots(attempt.image, attempt.circles, order.lattice_index, order.lattice_coords, attempt.levels,
                        plate)
    if len(extra):
        fill_in, _, levels = dot_appearance(attempt.image, extra.centres, extra.axes, extra.theta, plate.dark_dots)
        # the disc must look like a dot; the ring test is find_dot_at's, against the darker side of the
        # paper around the place (a shadow edge through the ring fails the candidates' ring test)
        keep = fill_in >= p.min_fill_inside
        extra, levels = extra.subset(keep), levels[keep]
    tm["completion"] = tm.get("completion", 0.0) + time.perf_counter() - t0
    if not len(extra):
        return None
    merged, added = merge_candidates(attempt.circles, extra)
    if not added.any():
        return None
    again = ordered_attempt(attempt.image, merged, np.concatenate([attempt.levels, levels[added]]), plate,
                            attempt.factor, tm, expected_rotation_deg=expected_rotation_deg, mirrored=mirrored,
                            expected_centres_px=None)
    return again if again.ok else None


BLUR_SHRINK = (1.0, 1.4, 1.8)
"""Factors by which a blur as wide as the gap between the dots can shrink their candidates (the Hough
rim and the region's core of an 8–16 px dot under a blur of σ ≈ 2 px are 0.5–0.9 of the dot): the
candidates' sizes are scaled by each in turn when no band gives the grid (:func:`shrunk_by_blur`)."""
FAINT_REGION_OFFSETS = (0.04, 0.02)
"""Region thresholds (fractions of the image's grey range below the local mean,
:func:`tasks.vision.detection.blobs.contour_candidates`) for faint dots: under such a blur the dots'
cores are only a few per cent of a busy image's range darker than the mean around them."""
BLUR_BAND_DOT_PX = 10.0
"""The blur fallback searches only the bands whose smallest dot (full-size px) is at most this: the blur
that fills the gap is a few px (σ ≈ 2–3 px), as wide as the gap only between dots of 8–16 px, whose
shrunk candidates (from ×1/1.8) those bands find; every image has one (the first band of an image
up to 1280 px across, the full-resolution band of small dots above)."""
FAINT_TEXTURE_DENSITY = 0.25
"""A faint-region window with more regions than this per square of the band's smallest dot (coarse
px²) is texture, not dots (a grid's dots are at least a dot apart: at most one per square): the fainter
offsets of that band are not searched (at full resolution on a textured 8 MP photograph they give
over 10⁵ regions, and their contour search alone costs more than the whole detection)."""


def shrunk_by_blur(searched: list[tuple[CoarseAttempt, BandSearch]], plate: DotPlate, p: FrameworkParams, tm: dict, *,
                   expected_rotation_deg: float | None, mirrored: bool) -> CoarseAttempt | None:
    """The grid from one band's candidates (``searched``: each band's attempt and its search) with the
    faint regions of its coarse image added (:data:`FAINT_REGION_OFFSETS`, each passing the candidates'
    test) and their sizes scaled by a factor of :data:`BLUR_SHRINK`, or None when none gives it.

    A blur as wide as the gap between the dots (σ ≈ 2 px on 8–16 px dots 4–8 px apart) fills the gap:
    few dots keep a rim for the Hough search or a core below the regions' usual threshold, and what is
    found of them is 0.5–0.9 of the dot. The lattice links dots whose spacing is at most 1.35 × pitch /
    diameter of their size: a candidate at 0.6 of its dot is 2.5 of its own sizes from its neighbours
    at a pitch of 1.5 diameters, beyond that. Scaled, the lattice links them and the rim fits start
    from the dot's size; every test of the window (its completeness and uniqueness, the strays, the
    parallelograms, the rim fits) is the same, and a window that steps over candidates (every other dot
    of a larger grid, :func:`skips_candidates`) is not taken. Bands in their order (only those of small
    dots, :data:`BLUR_BAND_DOT_PX`), then the offsets (none fainter once a window is texture,
    :data:`FAINT_TEXTURE_DENSITY`), then the factors from the smallest."""
    for a, band in searched:
        if a.levels is None or a.image is None or band.d_min > BLUR_BAND_DOT_PX or a.holds_bigger_grid:
            continue
        for offset in FAINT_REGION_OFFSETS:
            t0 = time.perf_counter()
            counts: list[int] = []
            d_min = band.d_min / a.factor
            regions = contour_candidates(a.image, plate.dark_dots, d_min, band.d_max / a.factor, offset,
                                         contour_counts=counts, means=band.means(a.image))
            faint, faint_levels = verified(a.image, regions, plate.dark_dots, p)
            c, added = merge_candidates(a.circles, faint)
            levels = np.concatenate([a.levels, faint_levels[added]])
            tm["contours"] = tm.get("contours", 0.0) + time.perf_counter() - t0
            texture = max(counts, default=0) * d_min**2 > FAINT_TEXTURE_DENSITY * a.image.size
            if len(c) < 4:
                if texture:
                    break
                continue
            for g in BLUR_SHRINK:
                grown = CoarseCircles(c.centres, c.axes * g, c.theta, c.votes, c.rim_ratio)
                again = ordered_attempt(a.image, grown, levels, plate, a.factor, tm,
                                        expected_rotation_deg=expected_rotation_deg, mirrored=mirrored,
                                        expected_centres_px=None)
                if again.ok and not skips_candidates(c.centres, again.order.index, plate):
                    return again
            if texture:  # a fainter offset finds more of the texture
                break
    return None


def skips_candidates(centres: np.ndarray, index: np.ndarray, plate: DotPlate) -> bool:
    """True when a candidate (``centres`` (K, 2) px) lies within a quarter of a step of the midpoint
    between two neighbouring dots of the window (``index`` (rows*cols,) into ``centres``): the window
    steps over dots, a sub-lattice of a larger grid (every other dot of a grid looks like a grid of dots
    shrunk by blur to half their spacing's share), not the plate."""
    window = centres[index].reshape(plate.rows, plate.cols, 2)
    pairs = [(window[:, 1:], window[:, :-1]), (window[1:, :], window[:-1, :])]
    mids = np.concatenate([((p + q) / 2).reshape(-1, 2) for p, q in pairs])
    steps = np.concatenate([np.linalg.norm(p - q, axis=-1).ravel() for p, q in pairs])
    nearest = np.linalg.norm(mids[:, None, :] - centres[None, :, :], axis=2).min(axis=1)
    return bool((nearest < 0.25 * steps).any())


def on_log_scale(small: np.ndarray, attempt: CoarseAttempt, plate: DotPlate, p: FrameworkParams, tm: dict,
                 **kw) -> CoarseAttempt:
    """``attempt`` (a refusal) searched again on a log scale: its band's coarse image through
    :func:`tasks.vision.detection.preprocess.log_stretch`, for dots of half to twice its lattice's median
    size, Hough circles then regions as a band does; the new attempt when it finds the grid or is more
    plate-like, else ``attempt``. ``small``: the image downsampled by the attempt's factor (its band's,
:meth:`BandSearch.small`); ``kw``: :func:`ordered_attempt`'s.

    A cast shadow's edge across a plate of dark dots leaves the shadowed dots a fifth of the lit ones'
    contrast on the band's gamma-stretched image: Canny's thresholds, set by the lit rims, drop them,
    and the dots along the edge, whose regions merge with the shadow and whose ring from the lit dot to
    the shadowed sheet fails the candidates' test, are left out; the lattice splits into a lit and a
    shadowed part, neither with enough of a window to look again. On a log scale the shadow's edge is
    a step of ln f, about half a dark dot's rim (ink at 0.14 of the sheet)."""
    order = attempt.order
    if order is None or order.lattice_index is None:
        return attempt
    d = float(np.median(2.0 * attempt.circles.axes[order.lattice_index, 0])) * attempt.factor
    t0 = time.perf_counter()
    pre = log_stretch(small, p.median_ksize)
    tm["preprocess"] = tm.get("preprocess", 0.0) + time.perf_counter() - t0
    again = hough_attempt(pre, plate, attempt.factor, 0.5 * d, 2.0 * d, p, tm, **kw)
    if not again.ok and p.contour_fallback:
        again = with_regions(again, plate, 0.5 * d, 2.0 * d, p, tm, **kw)
    return again if again.ok or again.plate_likeness(plate) > attempt.plate_likeness(plate) else attempt


def looked_again(small: np.ndarray, attempt: CoarseAttempt, plate: DotPlate, p: FrameworkParams, tm: dict,
                 **kw) -> CoarseAttempt:
    """The grid from the missing places of a refused ``attempt``'s lattice (:func:`complete_window`), else
    from ``attempt`` searched again on a log scale (:func:`on_log_scale`) or that search's missing
    places; else the more plate-like refusal. ``small``: as :func:`on_log_scale`'s; ``kw``:
    :func:`ordered_attempt`'s, without predicted dot positions. A lattice that holds a bigger grid
    (:attr:`CoarseAttempt.holds_bigger_grid`) is not looked at again."""
    if attempt.holds_bigger_grid:
        return attempt
    looks = dict(expected_rotation_deg=kw["expected_rotation_deg"], mirrored=kw["mirrored"])
    completed = complete_window(attempt, plate, p, tm, **looks)
    if completed is not None:
        return completed
    logged = on_log_scale(small, attempt, plate, p, tm, **kw)
    if logged.ok or logged is attempt:
        return logged
    completed = complete_window(logged, plate, p, tm, **looks)
    return completed if completed is not None else logged


def merge_candidates(first: CoarseCircles, more: CoarseCircles, other_sizes: bool = False
                     ) -> tuple[CoarseCircles, np.ndarray]:
    """(``first`` and the circles of ``more`` that are not within half a minor axis of one of them,
    (len(more),) bool: which of ``more`` were added, after ``first``). With ``other_sizes``, a circle
    of ``more`` at the place of one of ``first`` whose size differs beyond :data:`SIMILAR_SIZE` from
    it is added too."""
    if len(first) == 0 or len(more) == 0:
        return (more, np.ones(len(more), bool)) if len(first) == 0 else (first, np.zeros(len(more), bool))
    d = np.linalg.norm(more.centres[:, None, :] - first.centres[None, :, :], axis=2)
    apart = d >= 0.5 * np.minimum(more.axes[:, 1, None], first.axes[None, :, 1])
    if other_sizes:
        ratio = more.axes[:, 0, None] / first.axes[None, :, 0]
        apart |= (ratio >= SIMILAR_SIZE) | (ratio <= 1.0 / SIMILAR_SIZE)
    new = apart.all(axis=1)
    add = more.subset(new)
    return CoarseCircles(np.concatenate([first.centres, add.centres]), np.concatenate([first.axes, add.axes]),
                         np.concatenate([first.theta, add.theta]), np.concatenate([first.votes, add.votes]),
                         np.concatenate([first.rim_ratio, add.rim_ratio])), new


def small_dot_grid(band: BandSearch, finer: BandSearch) -> CoarseAttempt | None:
    """The grid of ``finer`` (the full-resolution band of dots from :data:`SMALL_DOT_PX`), taken before
    ``band``'s region contours are searched, when the Hough circles of both show the dots are below
    ``band``'s: ``band``'s circles give no grid and ``finer``'s do, of a median area-equivalent diameter
    (2 √(a b), full-size px) under ``band``'s smallest; else None (``band`` goes on as before).

    On a 12 MP photograph with 8 px dots the region contours of the half-resolution band (3 MP, the
    paper texture's thousands of regions) cost as much as the full-resolution search that finds the
    grid; the contours' size test is by area, and a foreshortened dot is smaller by area than across."""
    if band.hough_is_final() or not finer.hough_is_final():
        return None
    found = finer.full()  # the Hough circles' grid, no contours
    idx = found.order.index[found.order.index >= 0]
    axes = found.circles.axes[idx]
    d_px = 2.0 * np.sqrt(axes[:, 0] * axes[:, 1]) * found.factor
    return found if float(np.median(d_px)) < band.d_min else None


def failed_fits(fits: EllipseFits, c0: np.ndarray, factor: int, min_support: float) -> np.ndarray:
    """(K,) bool: rim fits that failed, have less than ``min_support`` of their rays, or moved from
    their coarse centres ``c0`` (K, 2) px by more than half a minor axis (and 2 coarse px); a dot
    refitted under a shadow's edge may have been found as its lit part: its coarse centre need only
    lie inside it."""
    reach = np.where(fits.shadowed, fits.axes[:, 1], 0.5 * fits.axes[:, 1])
    moved = np.linalg.norm(fits.centres - c0, axis=1) > np.maximum(reach, 2.0 * factor)
    return ~fits.ok | (fits.support < min_support) | moved


FIT_FIELDS = ("centres", "axes", "theta", "residual_rms_px", "support", "edge_sigma_px", "ok", "shadowed")
REFIT_STARTS = 3  # the nearest dots fitted well whose ellipses a failed dot's refit starts from, in turn


def refit_from_neighbours(image: np.ndarray, fits: EllipseFits, c0: np.ndarray, bad: np.ndarray, dark_dots: bool,
                          gap_ratio: float, factor: int, p: FrameworkParams, tm: dict) -> None:
    """Fit the ``bad`` dots' rims again (in place in ``fits``) from their coarse centres ``c0`` (K, 2) px
    with the semi-axes and angle of a dot fitted well: the nearest, then the next (up to
    :data:`REFIT_STARTS`); from each, the rim search of pass 1 first, then pass 2 straight from its
    ellipse and edge blur.

    Under a blur as wide as the gap between the dots a candidate's coarse circle can be a fraction of
    its dot, and a rim search started from it locks on to the wrong edge (a neighbour's blurred rim);
    the plate's dots are alike, so a fitted neighbour's ellipse is the better start. Only dots that
    failed are fitted again: a grid whose fits all pass is not touched."""
    good = np.flatnonzero(~bad)
    # the neighbour model needs every dot's fit: a subset's dots would model only each other
    sub = replace(p.subpixel, neighbour_iterations=0)
    for rank in range(min(REFIT_STARTS, len(good))):
        k = np.flatnonzero(bad)
        dist = np.linalg.norm(c0[k, None, :] - fits.centres[None, good, :], axis=2)
        near = good[np.argsort(dist, axis=1, kind="stable")[:, rank]]
        for blur in (None, fits.edge_sigma_px[near]):
            again = refine_ellipses(image, c0[k], fits.axes[near], fits.theta[near], dark_dots, gap_ratio, factor,
                                    sub, seed=p.seed, timings=tm, blur_px=blur)
            now = ~failed_fits(again, c0[k], factor, p.min_support)
            for name in FIT_FIELDS:
                getattr(fits, name)[k[now]] = getattr(again, name)[now]
            bad[k[now]] = False
            k, near = k[~now], near[~now]
            if not len(k):
                return
    if bad.any():  # still failed: the last attempt's fits, for the reason given
        for name in FIT_FIELDS:
            getattr(fits, name)[k] = getattr(again, name)[~now]


def detect_rrht(image: np.ndarray, plate: DotPlate, *, expected_rotation_deg: float | None = None,
                px_per_mm_hint: float | None = None, correct_perspective: bool = True,
                mirrored: bool = False, expected_centres_px: np.ndarray | None = None,
                params: FrameworkParams | None = None) -> GridDetection:
    """Detect and order the plate's dots with the RRHT framework (see module docstring).

    image: (H, W) uint8 grayscale. plate: the expected plate (rows, cols, pitch, diameter,
    polarity). expected_rotation_deg: prior on the in-plane angle of the plate +X axis (ccw on
    screen, deg) that resolves the grid's rotational symmetry. px_per_mm_hint: approximate scale
    on the plate (px/mm); speeds up and hardens the search. correct_perspective: subtract the
    perspective bias of circle centres. mirrored: the plate is seen from its back.
    expected_centres_px: (rows*cols, 2) predicted dot positions (full-size px); with them a plate
    partly out of the image is measured on the dots inside it (:mod:`tasks.vision.detection.partial_view`),
    and a dot whose rim rays the image border would cut (:func:`cut_by_border`) is left out.
    Without them the whole grid must be found and a dot at the border is fitted on the rays
    inside the image (calibration views, where the target fills the field).
    """
    p = params or FrameworkParams()
    t_start = time.perf_counter()
    n = plate.rows * plate.cols
    tm: dict[str, float] = {}

    def fail(reason: str, **kw) -> GridDetection:
        return GridDetection.failure(n, "rrht", reason, elapsed_s=time.perf_counter() - t_start,
                                     timings_s=tm, **kw)

    image = check_image(image)
    kw = dict(expected_rotation_deg=expected_rotation_deg, mirrored=mirrored, expected_centres_px=expected_centres_px)
    bands = [BandSearch(image, plate, factor, d_min, d_max, p, tm, kw) for factor, d_min, d_max in
             search_bands(image.shape, plate, px_per_mm_hint, p.coarse_target_diameter_px, p.coarse_width_px)]
    attempts: list[CoarseAttempt] = []
    for k, band in enumerate(bands):
        small = small_dot_grid(band, bands[3]) if k == 2 and len(bands) == 4 else None  # the small-dot pair
        if small is not None:
            attempts.append(small)
            break
        attempts.append(band.full())
        if attempts[-1].ok or expected_centres_px is not None:  # a prior fixes the scale: one band
            break
    attempt = attempts[-1] if attempts[-1].ok else max(attempts, key=lambda a: a.plate_likeness(plate))
    if not attempt.ok:
        joined = join_bands(attempts, plate, tm, expected_rotation_deg=expected_rotation_deg, mirrored=mirrored)
        attempt = joined if joined is not None else attempt
    if not attempt.ok and expected_centres_px is None:
        searched = list(zip(attempts, bands, strict=False))  # a band after the one that found a grid is not searched
        blurred = shrunk_by_blur(searched, plate, p, tm, expected_rotation_deg=expected_rotation_deg, mirrored=mirrored)
        attempt = blurred if blurred is not None else attempt
    if not attempt.ok and expected_centres_px is None:
        band = next(b for b in bands if b.factor == attempt.factor)  # bands of one factor share the image
        attempt = looked_again(band.small(), attempt, plate, p, tm, **kw)
    for band in bands:  # the coarse search is over: its stores of local means are not needed again
        band.release_means()
    circles, order, factor = attempt.circles, attempt.order, attempt.factor
    cand_uv, cand_d = attempt.candidates_full()
    debug = {"n_candidates": len(circles), "candidates_px": cand_uv, "candidate_diameters_px": cand_d}
    if not attempt.ok:
        if order is not None and order.lattice_index is not None:
            debug["lattice_px"] = coarse_to_full(circles.centres[order.lattice_index], factor)
            debug["lattice_coords"] = order.lattice_coords
        return fail(attempt.reason, **debug)
    if expected_centres_px is None:  # a window of a larger plate whose other dots no candidate search found
        beyond = continued_beyond(attempt.image, circles, order.index, attempt.levels, plate, p.min_fill_inside)
        if beyond:
            return fail(beyond, **debug)
    rc = plate.row_col()
    found = order.index >= 0
    gap_ratio = plate.pitch_range_mm[0] / plate.dot_diameter_mm - 1.0
    if expected_centres_px is not None:  # a view that may be partial leaves out the dots the border cuts
        found[found] = ~cut_by_border(coarse_to_full(circles.centres[order.index[found]], factor),
                                      circles.axes[order.index[found], 0] * factor, gap_ratio, image.shape)
    too_few = too_few_dots(int(found.sum()), n)
    if too_few:
        return fail(too_few, **debug)
    idx = order.index[found]
    c0 = coarse_to_full(circles.centres[idx], factor)
    fits = refine_ellipses(image, c0, circles.axes[idx] * factor, circles.theta[idx], plate.dark_dots,
                           gap_ratio, factor, p.subpixel, seed=p.seed, timings=tm)
    bad = failed_fits(fits, c0, factor, p.min_support)
    if bad.any() and (~bad).sum() >= 3:
        refit_from_neighbours(image, fits, c0, bad.copy(), plate.dark_dots, gap_ratio, factor, p, tm)
        bad = failed_fits(fits, c0, factor, p.min_support)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        r, c = rc[found][k]
        return fail(f"rim fit failed for {int(bad.sum())} dot(s), first at row {r} col {c} "
                    f"(support {fits.support[k]:.2f})", **debug)
    t5 = time.perf_counter()
    xy = plate.dot_centres_mm()[found, :2]
    if correct_perspective:
        centres, hom = corrected_centres(fits.centres, xy, plate.dot_diameter_mm / 2, rc[found], p.bias_iterations,
                                         p.distorted_misfit_px)
    else:
        centres, hom = fits.centres.copy(), fit_homography(xy, fits.centres)
    tm["perspective"] = time.perf_counter() - t5

    def per_dot(values: np.ndarray) -> np.ndarray:  # found dots' values → (rows*cols, ...), NaN for the rest
        out = np.full((n, *values.shape[1:]), np.nan)
        out[found] = values
        return out

    return GridDetection(
        ok=True, reason="", detector="rrht", centres=per_dot(centres), residual_rms_px=per_dot(fits.residual_rms_px),
        support_ratio=per_dot(fits.support), elapsed_s=time.perf_counter() - t_start,
        ellipse_centres=per_dot(fits.centres), axes_px=per_dot(fits.axes), edge_sigma_px=per_dot(fits.edge_sigma_px),
        rotation_deg=order.rotation_deg, shadowed=np.isin(np.arange(n), np.flatnonzero(found)[fits.shadowed]),
        orientation_ambiguous=order.ambiguous, homography=hom, timings_s=tm, **debug,
    )
