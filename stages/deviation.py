"""Deviation statistics and the regular correction grid."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import MarkcalError


def deviation_stats(xy_mm: np.ndarray, dxy_mm: np.ndarray, half_width_mm: float | None = None) -> dict:
    """Max and RMS of ux, uy and |delta| (paper Table 1) inside a centred square.

    Parameters
    ----------
    xy_mm : ndarray, shape (n, 2)
        Positions (GLS frame) that select the area.
    dxy_mm : ndarray, shape (n, 2)
        Deviations at those positions.
    half_width_mm : float, optional
        Keep points with |x|, |y| <= this (+1 um slack); None: all.
    """
    xy = np.asarray(xy_mm, float)
    d = np.asarray(dxy_mm, float)
    if half_width_mm is not None:
        sel = np.all(np.abs(xy) <= half_width_mm + 1e-3, axis=1)
        d = d[sel]
    if len(d) == 0:
        return {"n": 0}
    mag = np.hypot(d[:, 0], d[:, 1])
    return {
        "n": int(len(d)),
        "max_x_mm": float(np.abs(d[:, 0]).max()), "max_y_mm": float(np.abs(d[:, 1]).max()),
        "max_mm": float(mag.max()),
        "rms_x_mm": float(np.sqrt(np.mean(d[:, 0] ** 2))), "rms_y_mm": float(np.sqrt(np.mean(d[:, 1] ** 2))),
        "rms_mm": float(np.sqrt(np.mean(mag ** 2))),
    }


@dataclass(frozen=True)
class GridCorrection:
    """A regular grid of command offsets with bilinear interpolation.

    The command for a wanted position (x, y) is (x + dx, y + dy); lengths mm,
    GLS frame. ``dx_mm``/``dy_mm`` are indexed [iy, ix].
    """

    x_mm: np.ndarray
    y_mm: np.ndarray
    dx_mm: np.ndarray
    dy_mm: np.ndarray

    @classmethod
    def from_nodes(cls, xy_mm: np.ndarray, dxy_mm: np.ndarray) -> "GridCorrection":
        """Build from rows of a correction table (any order, must be a full grid)."""
        xy = np.asarray(xy_mm, float)
        dxy = np.asarray(dxy_mm, float)
        xs = np.unique(np.round(xy[:, 0], 9))
        ys = np.unique(np.round(xy[:, 1], 9))
        if len(xs) * len(ys) != len(xy) or len(xs) < 2 or len(ys) < 2:
            raise MarkcalError("correction table is not a full regular grid")
        ix = np.searchsorted(xs, np.round(xy[:, 0], 9))
        iy = np.searchsorted(ys, np.round(xy[:, 1], 9))
        dx = np.full((len(ys), len(xs)), np.nan)
        dy = np.full_like(dx, np.nan)
        dx[iy, ix] = dxy[:, 0]
        dy[iy, ix] = dxy[:, 1]
        return cls(xs, ys, dx, dy)

    def offset(self, xy_mm: np.ndarray) -> np.ndarray:
        """Bilinear (dx, dy) at positions (n, 2); clamped to the grid's edge outside it."""
        xy = np.atleast_2d(np.asarray(xy_mm, float))
        fx = np.interp(xy[:, 0], self.x_mm, np.arange(len(self.x_mm)))
        fy = np.interp(xy[:, 1], self.y_mm, np.arange(len(self.y_mm)))
        i0 = np.clip(np.floor(fx).astype(int), 0, len(self.x_mm) - 2)
        j0 = np.clip(np.floor(fy).astype(int), 0, len(self.y_mm) - 2)
        tx, ty = fx - i0, fy - j0
        out = []
        for g in (self.dx_mm, self.dy_mm):
            v = (g[j0, i0] * (1 - tx) * (1 - ty) + g[j0, i0 + 1] * tx * (1 - ty)
                 + g[j0 + 1, i0] * (1 - tx) * ty + g[j0 + 1, i0 + 1] * tx * ty)
            out.append(v)
        return np.column_stack(out)

    def command(self, xy_mm: np.ndarray) -> np.ndarray:
        """Commanded positions for wanted positions (n, 2), mm."""
        xy = np.atleast_2d(np.asarray(xy_mm, float))
        return xy + self.offset(xy)


def grid_nodes(half_x_mm: float, half_y_mm: float, step_mm: float) -> np.ndarray:
    """Nodes (n, 2) of a regular grid with ``step_mm`` covering [-hx, hx] x [-hy, hy].

    Row-major: y outer, x inner; the grid is symmetric about 0 and reaches at
    least the field edge.
    """
    nx = int(np.ceil(half_x_mm / step_mm - 1e-9))
    ny = int(np.ceil(half_y_mm / step_mm - 1e-9))
    xs = np.arange(-nx, nx + 1) * step_mm
    ys = np.arange(-ny, ny + 1) * step_mm
    gx, gy = np.meshgrid(xs, ys)
    return np.column_stack([gx.ravel(), gy.ravel()])
