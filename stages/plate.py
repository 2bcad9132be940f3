"""Plate spec and the nominal fiducial grid."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


#: the site (row, col) rendered plates leave unmarked: on no symmetry axis of a square grid, so
#: it tells all 8 turns and mirrors apart
DEFAULT_ORIENTATION_MARK = (0, 1)


#: what a marked plate is for: measuring the distortion, or checking a correction
PURPOSES = ("calibration", "validation")


@dataclass(frozen=True)
class PlateSpec:
    """What the GLS was asked to mark, as in PLATE.toml.

    Lengths in mm. The grid is centred on the galvo origin; row r has
    y = (r - (rows-1)/2) * pitch, column c has x = (c - (cols-1)/2) * pitch.
    """

    rows: int = 19
    cols: int = 19
    pitch_mm: float = 190.0 / 18.0
    ring_radii_mm: tuple = (2.5, 2.7)
    d_mm: float = 490.0
    e_mm: float = 22.0
    grid_step_mm: float = 1.0
    orientation_mark: tuple = ()     # (row, col) of a site left unmarked; () none
    purpose: str = "calibration"     # "calibration": marked without correction; "validation": through it

    @property
    def mark_id(self):
        """Id of the unmarked orientation site, or None."""
        return self.orientation_mark[0] * self.cols + self.orientation_mark[1] if self.orientation_mark else None

    @property
    def marked_ids(self) -> list:
        """Ids of the sites that carry a fiducial."""
        return [i for i in range(self.n_fiducials) if i != self.mark_id]

    @property
    def n_fiducials(self) -> int:
        return self.rows * self.cols

    @property
    def half_extent_mm(self) -> tuple:
        """Half widths (x, y) of the fiducial field, centre to outermost centre."""
        return ((self.cols - 1) / 2 * self.pitch_mm, (self.rows - 1) / 2 * self.pitch_mm)


def nominal_grid(spec: PlateSpec) -> tuple:
    """Nominal fiducial centres in the GLS frame.

    Returns
    -------
    rows, cols : ndarray of int, shape (n,)
        Index of each fiducial; id = row * cols + col.
    xy_mm : ndarray, shape (n, 2)
        Nominal (x, y) in mm, GLS frame.
    """
    r, c = np.divmod(np.arange(spec.rows * spec.cols), spec.cols)
    x = (c - (spec.cols - 1) / 2.0) * spec.pitch_mm
    y = (r - (spec.rows - 1) / 2.0) * spec.pitch_mm
    return r, c, np.column_stack([x, y])
