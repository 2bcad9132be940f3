"""3D -> 2D projection of a plate scan onto a raster in the plate plane."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import MarkcalError
from .plane import Plane, to_plane


@dataclass(frozen=True)
class Raster:
    """Intensity image of the plate, row = v, column = u (plate frame, mm).

    ``u_mm``/``v_mm`` hold the mean in-plane position of the points that fell
    in each cell (NaN where none did), so sub-pixel fits can use where the
    samples really were rather than cell centres. ``valid`` marks cells with
    at least one on-plane point. An image (``stages.plate_image``) has
    ``u_mm``/``v_mm``/``valid`` None: samples sit at the cell centres, all valid.
    """

    intensity: np.ndarray
    u_mm: np.ndarray
    v_mm: np.ndarray
    valid: np.ndarray
    u0_mm: float
    v0_mm: float
    pixel_mm: float

    def samples(self, rr: np.ndarray, cc: np.ndarray) -> tuple:
        """In-plane positions (mm) and validity of cells at integer rows/cols (in bounds)."""
        if self.u_mm is None:
            return ((cc + 0.5) * self.pixel_mm + self.u0_mm, (rr + 0.5) * self.pixel_mm + self.v0_mm,
                    np.ones(np.shape(rr), bool))
        return self.u_mm[rr, cc], self.v_mm[rr, cc], self.valid[rr, cc]

    def to_pixel(self, uv_mm: np.ndarray) -> np.ndarray:
        """(u, v) mm -> (col, row) pixel coordinates (cell centres at integers)."""
        uv = np.asarray(uv_mm, float)
        return np.column_stack([(uv[:, 0] - self.u0_mm) / self.pixel_mm - 0.5,
                                (uv[:, 1] - self.v0_mm) / self.pixel_mm - 0.5])

    def to_mm(self, colrow: np.ndarray) -> np.ndarray:
        """(col, row) pixel coordinates -> (u, v) mm."""
        cr = np.asarray(colrow, float)
        return np.column_stack([(cr[:, 0] + 0.5) * self.pixel_mm + self.u0_mm,
                                (cr[:, 1] + 0.5) * self.pixel_mm + self.v0_mm])


def project(xyz_mm: np.ndarray, intensity: np.ndarray, plane: Plane,
            pixel_mm: float = 0.1, max_height_mm: float | None = None) -> Raster:
    """Project on-plane points onto a raster of ``pixel_mm`` cells.

    Points farther than ``max_height_mm`` from the plane (the clamping frame,
    spurious reflections) are left out; so are saturated intensities (the
    cloud's maximum value when it is shared by a cluster of points).

    Parameters
    ----------
    xyz_mm : ndarray, shape (n, 3)
        Scanner-frame points, mm.
    intensity : ndarray, shape (n,)
        Backscatter intensity, any scale.
    plane : Plane
        The fitted plate plane.
    """
    if max_height_mm is None:
        max_height_mm = max(plane.threshold_mm, 0.05)
    uvh = to_plane(xyz_mm, plane)
    keep = np.abs(uvh[:, 2]) < max_height_mm
    inten = np.asarray(intensity, np.float64)
    top = inten.max()
    if np.count_nonzero(inten == top) > 1e-4 * len(inten):
        keep &= inten < top
    uv = uvh[keep, :2]
    inten = inten[keep]
    if len(uv) < 100:
        raise MarkcalError("fewer than 100 points lie on the plate plane")
    lo, hi = np.percentile(uv, [0.01, 99.99], axis=0)
    lo = np.floor(lo / pixel_mm) * pixel_mm
    ncol, nrow = (np.ceil((hi - lo) / pixel_mm).astype(int) + 1)
    if nrow * ncol > 200_000_000:
        raise MarkcalError(f"plate raster would be {nrow} x {ncol} cells: coordinates are not in mm")
    col = np.floor((uv[:, 0] - lo[0]) / pixel_mm).astype(np.int64)
    row = np.floor((uv[:, 1] - lo[1]) / pixel_mm).astype(np.int64)
    inside = (col >= 0) & (col < ncol) & (row >= 0) & (row < nrow)
    flat = row[inside] * ncol + col[inside]
    size = nrow * ncol
    count = np.bincount(flat, minlength=size)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_i = np.bincount(flat, inten[inside], size) / count
        mean_u = np.bincount(flat, uv[inside, 0], size) / count
        mean_v = np.bincount(flat, uv[inside, 1], size) / count
    shape = (nrow, ncol)
    return Raster(intensity=mean_i.reshape(shape).astype(np.float32),
                  u_mm=mean_u.reshape(shape), v_mm=mean_v.reshape(shape),
                  valid=(count > 0).reshape(shape), u0_mm=float(lo[0]), v0_mm=float(lo[1]),
                  pixel_mm=float(pixel_mm))
