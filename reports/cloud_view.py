"""An isometric picture of a point cloud drawn with numpy alone (no OpenGL, no VTK).

The scan report shows the decimated cloud, its intensity and the fitted plate normal. Each point
is projected orthographically along the isometric view direction (1, 1, 1) with z up, splatted
into a small square of pixels, and the nearest point wins each pixel (a z-buffer by sorting).
"""
from __future__ import annotations

import numpy as np

__all__ = ["IsoView", "splat"]

#: direction from the scene towards the camera (pyvista's ``view_isometric``)
VIEW_DIR = np.array([1.0, 1.0, 1.0]) / np.sqrt(3.0)


class IsoView:
    """Orthographic isometric camera fitted to a cloud: mm -> pixel (column, row) and depth.

    Parameters
    ----------
    xyz_mm : (N, 3) array
        The points the picture must hold.
    width_px, height_px : int
        Picture size.
    margin : float
        Fraction of the picture left empty around the cloud.
    """

    def __init__(self, xyz_mm: np.ndarray, width_px: int, height_px: int, margin: float = 0.06):
        f = -VIEW_DIR                                          # camera -> scene
        right = np.cross(f, [0.0, 0.0, 1.0])
        self.right = right / np.linalg.norm(right)
        self.up = np.cross(self.right, f)
        self.forward = f
        self.width_px, self.height_px = int(width_px), int(height_px)
        s = self._screen(xyz_mm)
        lo, hi = s.min(axis=0), s.max(axis=0)
        self.centre = (lo + hi) / 2
        span = np.maximum(hi - lo, 1e-9)
        self.px_per_mm = float(min(self.width_px / span[0], self.height_px / span[1]) * (1 - 2 * margin))

    def _screen(self, xyz_mm) -> np.ndarray:
        return np.asarray(xyz_mm, float) @ np.column_stack([self.right, self.up])

    def to_pixel(self, xyz_mm) -> np.ndarray:
        """(N, 2) pixel (column, row) of points, row 0 at the top, as floats."""
        s = (self._screen(np.atleast_2d(xyz_mm)) - self.centre) * self.px_per_mm
        return np.column_stack([s[:, 0] + self.width_px / 2, self.height_px / 2 - s[:, 1]])

    def direction(self, vec) -> np.ndarray:
        """Screen direction (d column, d row) of a 3D vector, unit length when the vector is not along the view."""
        v = np.asarray(vec, float)
        d = np.array([v @ self.right, -(v @ self.up)])
        n = np.linalg.norm(d)
        return d / n if n > 0 else d

    def depth(self, xyz_mm) -> np.ndarray:
        """Distance along the view direction (larger: farther from the camera)."""
        return np.asarray(xyz_mm, float) @ self.forward


def splat(view: IsoView, xyz_mm: np.ndarray, values: np.ndarray, size_px: int = 2) -> np.ndarray:
    """Picture of ``values`` at the points: (height, width) float, NaN where no point lands.

    Each point covers ``size_px`` x ``size_px`` pixels; where points overlap, the one nearest the
    camera is shown.
    """
    h, w = view.height_px, view.width_px
    pix = np.floor(view.to_pixel(xyz_mm)).astype(np.int64)
    order = np.argsort(view.depth(xyz_mm), kind="stable")     # nearest first
    pix, vals = pix[order], np.asarray(values, float)[order]
    offs = np.array([(dc, dr) for dr in range(size_px) for dc in range(size_px)])
    cells = (pix[:, None, :] + offs[None, :, :]).reshape(-1, 2)   # point by point, nearest first
    v = np.repeat(vals, len(offs))
    inside = (cells[:, 0] >= 0) & (cells[:, 0] < w) & (cells[:, 1] >= 0) & (cells[:, 1] < h)
    lin = cells[inside, 1] * w + cells[inside, 0]
    first = np.unique(lin, return_index=True)[1]                # first = nearest point at each pixel
    out = np.full(h * w, np.nan)
    out[lin[first]] = v[inside][first]
    return out.reshape(h, w)

