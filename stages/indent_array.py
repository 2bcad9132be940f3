"""Indentation arrays: place imprints on the nominal grid, register, per-size statistics (paper 000 Table 1)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import MarkcalError
from .register import index_grid, neighbour_pitch, robust_rigid_fit


@dataclass(frozen=True)
class ArraySpec:
    """What was indented: an R x C array at ``pitch_um`` of one nominal size (ARRAY.toml)."""

    rows: int
    cols: int
    pitch_um: float
    nominal_diameter_um: float
    indenter: str = "vickers"
    load_mN: float | None = None            # [indenter] load_mN: for the Vickers hardness


__all__ = ["ArrayFit", "index_array", "size_stats"]


@dataclass(frozen=True)
class ArrayFit:
    """Imprints placed on the nominal array and registered to it (µm, array frame).

    ``row``/``col`` -1: not on the grid. ``dx_um``, ``dy_um``: registered
    measured position minus nominal (NaN when not placed or fewer than 2 placed).
    ``stray``: more than 0.35 pitch from every node of the registered lattice, extended
    beyond the array (a dust dot or pit between imprints, not a node the spec lacks).
    """

    row: np.ndarray
    col: np.ndarray
    dx_um: np.ndarray
    dy_um: np.ndarray
    rotation_deg: float
    pitch_um: float
    used: np.ndarray
    stray: np.ndarray


def index_array(xy_um: np.ndarray, rows: int, cols: int, pitch_um: float) -> ArrayFit:
    """Give each imprint its row and column and register the array rigidly to the nominal grid.

    The nominal grid is centred on the origin: column c at x = (c - (cols-1)/2) pitch,
    row r at y = (r - (rows-1)/2) pitch, rows growing with y (image rows).

    Raises
    ------
    MarkcalError
        If the spacing of the imprints does not match ``pitch_um``.
    """
    xy = np.asarray(xy_um, float)
    n = len(xy)
    if n >= 4:
        # the same test as index_grid's below, with the array spec's words (pits or dust dots between the
        # imprints do not decide the spacing)
        nn = neighbour_pitch(xy, pitch_um)[0]
        if abs(nn / pitch_um - 1) > 0.1:
            raise MarkcalError(f"imprint spacing in the image is {nn:.2f} µm but the array spec says "
                               f"pitch_um = {pitch_um:g}")
    if n >= 5 and rows * cols >= 5:
        gi = index_grid(xy, rows, cols, pitch_um, pitch_tolerance=0.1)
        row, col, rot = gi.row.copy(), gi.col.copy(), gi.rotation_deg
    else:
        # few imprints: nearest node after centring on the grid (no rotation)
        rel = (xy - xy.mean(axis=0)) / pitch_um
        k = np.rint(rel + [(cols - 1) / 2, (rows - 1) / 2]).astype(int)
        col, row = k[:, 0].copy(), k[:, 1].copy()
        bad = (col < 0) | (col >= cols) | (row < 0) | (row >= rows)
        col[bad], row[bad] = -1, -1
        rot = 0.0
    # two imprints on one node: keep the first, drop the other
    ids = row * cols + col
    seen = set()
    for i in range(n):
        if row[i] < 0:
            continue
        if ids[i] in seen:
            row[i] = col[i] = -1
        seen.add(ids[i])
    on = row >= 0
    dxy = np.full((n, 2), np.nan)
    used = np.zeros(n, bool)
    stray = np.zeros(n, bool)
    if on.sum() >= 2:
        q = np.column_stack([(col[on] - (cols - 1) / 2) * pitch_um, (row[on] - (rows - 1) / 2) * pitch_um])
        tf, u = robust_rigid_fit(xy[on], q, 0.3 * pitch_um)
        dxy[on] = tf.apply(xy[on]) - q
        used[np.flatnonzero(on)[u]] = True
        rot = -tf.angle_deg
        lat = tf.apply(xy) / pitch_um + [(cols - 1) / 2, (rows - 1) / 2]
        stray = ~on & (np.abs(lat - np.rint(lat)).max(axis=1) > 0.35)
    return ArrayFit(row=row, col=col, dx_um=dxy[:, 0], dy_um=dxy[:, 1], rotation_deg=float(rot),
                    pitch_um=float(pitch_um), used=used, stray=stray)


def size_stats(nominal_um: np.ndarray, diameter_um: np.ndarray, hd: np.ndarray, depth_nm: np.ndarray) -> dict:
    """Per-nominal-size statistics (paper Table 1): columns of sizes.csv.

    Standard deviations use n - 1 (NaN for one imprint); ``max_abs_error_um`` is
    the largest |diameter - nominal|.
    """
    nominal_um = np.asarray(nominal_um, float)
    sizes = np.unique(nominal_um[np.isfinite(nominal_um)])
    cols = {k: [] for k in ("nominal_um", "n", "mean_diameter_um", "sd_diameter_um", "max_abs_error_um",
                            "mean_hd", "sd_hd", "mean_depth_nm")}

    def sd(a):
        a = a[np.isfinite(a)]
        return float(np.std(a, ddof=1)) if len(a) > 1 else float("nan")

    def mean(a):
        a = a[np.isfinite(a)]
        return float(np.mean(a)) if len(a) else float("nan")

    for s in sizes:
        m = nominal_um == s
        d = np.asarray(diameter_um, float)[m]
        cols["nominal_um"].append(float(s))
        cols["n"].append(int(m.sum()))
        cols["mean_diameter_um"].append(mean(d))
        cols["sd_diameter_um"].append(sd(d))
        cols["max_abs_error_um"].append(float(np.nanmax(np.abs(d - s))))
        cols["mean_hd"].append(mean(np.asarray(hd, float)[m]))
        cols["sd_hd"].append(sd(np.asarray(hd, float)[m]))
        cols["mean_depth_nm"].append(mean(np.asarray(depth_nm, float)[m]))
    return {k: np.array(v) for k, v in cols.items()}
