"""The result of ordering detected dots into a plate's grid, and what every ordering shares.

Frames: image px (u right, v down); plate rows/cols as in :class:`tasks.machine.plate.DotPlate`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tasks.machine.plate import DotPlate

SIMILAR_SIZE = 1.45
"""Two dots of one plate differ in size (major axis) by less than this factor where the lattice links
them: neighbours in growth, a dot and its replacement in the window check."""


@dataclass
class GridOrder:
    """Result of ordering: ``index[k]`` is the input point of plate dot k (row-major), or -1."""

    ok: bool
    reason: str
    index: np.ndarray  # (rows*cols,) int
    rotation_deg: float = float("nan")  # angle of the plate +X axis in the image (ccw on screen)
    ambiguous: bool = False  # several orientations possible and no prior chose between them
    lattice_shape: tuple[int, int] = (0, 0)  # extent of the connected lattice found
    lattice_index: np.ndarray | None = None  # (L,) the input points of that lattice (on a refusal, for a drawing)
    lattice_coords: np.ndarray | None = None  # (L, 2) int their lattice coordinates
    window_dots: int = -1  # the most points of the lattice in one rows × cols window (-1: not counted)
    complete_windows: int = -1  # the complete rows × cols windows the lattice holds (-1: not counted)

    @property
    def bigger_grid(self) -> bool:
        """The lattice holds two complete windows or more: the dots of a grid larger than the plate, which
        more candidates of any kind cannot make one window."""
        return self.complete_windows > 1


def fail_order(plate: DotPlate, reason: str, shape=(0, 0), lattice: tuple[np.ndarray, np.ndarray] | None = None,
               window_dots: int = -1, complete_windows: int = -1) -> GridOrder:
    """A failed ordering of ``plate`` with its reason; ``shape`` is the lattice found, ``lattice`` its
    points (L,) (indices of the input points) and their coordinates (L, 2); ``window_dots`` the most
    of its points in one window of the plate's shape, ``complete_windows`` its complete windows."""
    index, coords = lattice if lattice is not None else (None, None)
    return GridOrder(False, reason, np.full(plate.rows * plate.cols, -1), lattice_shape=shape,
                     lattice_index=index, lattice_coords=coords, window_dots=window_dots,
                     complete_windows=complete_windows)


def lattice_steps(points_px: np.ndarray, row_col: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(column step, row step) in px: the least-squares affine map from plate (row, col) indices
    (K, 2) to image points (K, 2) px."""
    design = np.column_stack([row_col[:, 1], row_col[:, 0], np.ones(len(row_col))])
    coef, *_ = np.linalg.lstsq(design, points_px, rcond=None)
    return coef[0], coef[1]


def rotation_deg(column_step_px: np.ndarray):
    """In-plane angle (deg) of the plate's +X (column) axis, counter-clockwise on screen from +u, from
    its step in the image (..., 2) px: a float for one step, an array for many."""
    step = np.asarray(column_step_px, dtype=float)
    return np.degrees(np.arctan2(-step[..., 1], step[..., 0]))


def rotation_of(points: np.ndarray, index: np.ndarray, plate: DotPlate) -> float:
    """:func:`rotation_deg` of an ordering: ``index`` (rows*cols,) into ``points`` (N, 2) px, −1 for a
    dot not found."""
    found = index >= 0
    dcol, _ = lattice_steps(points[index[found]], plate.row_col()[found])
    return float(rotation_deg(dcol))
