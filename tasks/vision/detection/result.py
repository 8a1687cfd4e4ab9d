"""The common result type of every grid detector."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class GridDetection:
    """Dot centres of one plate image, ordered like ``DotPlate.dot_centres_mm`` (row-major).

    ok: True when every dot of the rows × cols grid was found and ordered, or (given where the
    dots should be) every dot wholly inside the image and at least half the plate's; otherwise
    ``reason`` says why not and the per-dot arrays are NaN. The per-dot arrays of a dot not
    measured (outside the image, or its rim cut by the border) are NaN: :attr:`found`.
    centres: (rows*cols, 2) px, image frame (u right, v down, origin at the centre of the top-left
    pixel). For "rrht" these are projected circle centres (perspective bias removed); the
    baselines return their raw centres.
    ellipse_centres: (rows*cols, 2) px, fitted ellipse centres before the bias correction.
    axes_px: (rows*cols, 2) semi-axes (major, minor) of each dot's ellipse, px (NaN if unknown).
    residual_rms_px: (rows*cols,) RMS distance of the rim points to the fitted ellipse, px.
    support_ratio: (rows*cols,) fraction of the rim that gave inlier edge points (0..1).
    edge_sigma_px: (rows*cols,) Gaussian σ of the rim blur (focus indicator), px, or None.
    rotation_deg: in-plane angle of the plate's +X (column) axis in the image, counter-clockwise
    on screen from +u, degrees. orientation_ambiguous: True when a symmetric grid's orientation
    was chosen by convention (closest to 0°) because no expected rotation was given.
    homography: (3, 3) plate (x, y) mm → image px fitted to the centres, or None.
    n_candidates: circles found before ordering; candidates_px (K, 2) and
    candidate_diameters_px (K,) are where and how large (full-size px), for a debug drawing
    (None when the detector does not report them). On a refusal, lattice_px (L, 2) and
    lattice_coords (L, 2) int: the candidates the grid's lattice was grown through and their
    lattice coordinates (None when no lattice was grown).
    shadowed: (rows*cols,) bool, "rrht": the dots a cast shadow's edge crosses, whose rims were
    fitted again on a log scale (:func:`tasks.vision.detection.subpixel.refine_ellipses`); their
    centres are less certain than the others' (up to 0.2–0.5 px on renders). None otherwise.
    timings_s: seconds per stage; elapsed_s: total seconds inside the detector.
    """

    ok: bool
    reason: str
    detector: str
    centres: np.ndarray
    residual_rms_px: np.ndarray
    support_ratio: np.ndarray
    elapsed_s: float = 0.0
    ellipse_centres: np.ndarray | None = None
    axes_px: np.ndarray | None = None
    edge_sigma_px: np.ndarray | None = None
    rotation_deg: float = float("nan")
    orientation_ambiguous: bool = False
    homography: np.ndarray | None = None
    n_candidates: int = 0
    candidates_px: np.ndarray | None = None
    candidate_diameters_px: np.ndarray | None = None
    lattice_px: np.ndarray | None = None
    lattice_coords: np.ndarray | None = None
    shadowed: np.ndarray | None = None
    timings_s: dict[str, float] = field(default_factory=dict)

    @property
    def found(self) -> np.ndarray:
        """(rows*cols,) bool: the dots measured (finite centres)."""
        return np.all(np.isfinite(self.centres), axis=1)

    @classmethod
    def failure(cls, n_dots: int, detector: str, reason: str, **kw) -> GridDetection:
        nan2 = np.full((n_dots, 2), np.nan)
        nan1 = np.full(n_dots, np.nan)
        return cls(False, reason, detector, nan2, nan1, nan1.copy(), **kw)
