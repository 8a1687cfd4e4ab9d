"""Dot calibration plates.

Plate frame: origin at the centre of the dot grid, +X along increasing column, +Y along
increasing row, +Z out of the printed face (towards the camera that views it). Units: mm.
Dot (row r, col c) sits at ((c - (cols-1)/2) * pitch, (r - (rows-1)/2) * row_pitch, 0); row_pitch
is pitch unless the plate says otherwise (a rectangular lattice).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from tasks.core import se3


@dataclass(frozen=True)
class DotPlate:
    """A rows × cols grid of circular dots.

    pitch_mm: centre-to-centre spacing along a row, i.e. between columns (mm, plate X).
    row_pitch_mm: spacing between rows (mm, plate Y); None for a square lattice (= pitch_mm).
    dot_diameter_mm: dot diameter (mm).
    dark_dots: True for dark dots on a light plate, False for light dots on dark.
    margin_mm: plate border beyond the outer dot centres (mm); outside the plate is background.
    """

    rows: int
    cols: int
    pitch_mm: float
    dot_diameter_mm: float
    dark_dots: bool = True
    margin_mm: float = 0.0
    name: str = "plate"
    row_pitch_mm: float | None = None

    @property
    def pitch_y_mm(self) -> float:
        """Spacing between rows (mm, plate Y)."""
        return self.pitch_mm if self.row_pitch_mm is None else self.row_pitch_mm

    @property
    def pitch_range_mm(self) -> tuple[float, float]:
        """(smallest, largest) of the two lattice spacings (mm)."""
        return min(self.pitch_mm, self.pitch_y_mm), max(self.pitch_mm, self.pitch_y_mm)

    @property
    def is_square_lattice(self) -> bool:
        """True when rows and columns are equally spaced (then a quarter turn maps the lattice onto itself)."""
        return self.pitch_y_mm == self.pitch_mm

    def dot_centres_mm(self) -> np.ndarray:
        """(rows*cols, 3) dot centres in the plate frame, row-major (row 0 col 0 first)."""
        r, c = np.meshgrid(np.arange(self.rows), np.arange(self.cols), indexing="ij")
        x = (c.ravel() - (self.cols - 1) / 2.0) * self.pitch_mm
        y = (r.ravel() - (self.rows - 1) / 2.0) * self.pitch_y_mm
        return np.stack([x, y, np.zeros_like(x)], axis=1)

    def row_col(self) -> np.ndarray:
        """(rows*cols, 2) integer (row, col) of each dot, in the order of dot_centres_mm."""
        r, c = np.meshgrid(np.arange(self.rows), np.arange(self.cols), indexing="ij")
        return np.stack([r.ravel(), c.ravel()], axis=1)

    @property
    def half_extent_mm(self) -> tuple[float, float]:
        """Half width and half height of the plate (mm), margin included."""
        return (
            (self.cols - 1) / 2.0 * self.pitch_mm + self.margin_mm,
            (self.rows - 1) / 2.0 * self.pitch_y_mm + self.margin_mm,
        )

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> DotPlate:
        return cls(**d)


def facing_camera_pose(position_mm, rx_deg: float = 0.0, ry_deg: float = 0.0, rz_deg: float = 0.0,
                       spin_deg: float = 0.0) -> np.ndarray:
    """T_cam_plate (4, 4, mm) of a plate whose printed face (+Z_plate) looks at the camera.

    Frontal first (plate +X along camera +X, plate +Y along camera −Y), turned by ``spin_deg``
    about the plate normal (plate frame), then by Rz(rz)·Ry(ry)·Rx(rx) in the camera frame
    (degrees); the plate centre at ``position_mm`` in the camera frame.
    """
    T = np.eye(4)
    T[:3, :3] = se3.rot_zyx_deg(rx_deg, ry_deg, rz_deg) @ np.diag([1.0, -1.0, -1.0]) @ se3.rot_zyx_deg(0, 0, spin_deg)
    T[:3, 3] = position_mm
    return T
