"""Sampling a correction onto a controller's table grid, and checking that it fits.

A controller table is a regular grid of nodes with a correction at each node,
interpolated bilinearly in between. Here a table is a
:class:`~markcal.stages.deviation.GridCorrection` (node positions and command
offsets in mm, indexed ``[iy, ix]``); the format modules turn it into bytes.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from markcal.stages.deviation import GridCorrection
from markcal.stages.errors import MarkcalError

__all__ = ["Sampled", "sample_onto_nodes", "check_interpolation", "check_range", "centred_nodes"]


@dataclass(frozen=True)
class Sampled:
    """A correction sampled onto table nodes.

    Attributes
    ----------
    table : GridCorrection
        Node positions and offsets (mm).
    n_extrapolated : int
        Nodes outside the measured region (given the value at the nearest point of it).
    """

    table: GridCorrection
    n_extrapolated: int


def centred_nodes(n_nodes: int, spacing: float, units_per_mm: float) -> np.ndarray:
    """Positions (mm) of ``n_nodes`` nodes ``spacing`` controller units apart, centred on 0."""
    return (np.arange(n_nodes) - (n_nodes - 1) / 2.0) * spacing / units_per_mm


def sample_onto_nodes(offset_mm, x_nodes_mm: np.ndarray, y_nodes_mm: np.ndarray, region_mm: tuple,
                      max_extrapolated_fraction: float = 0.5, margin_mm: float | None = None) -> Sampled:
    """Evaluate a correction at every node of a table.

    Parameters
    ----------
    offset_mm : callable
        (n, 2) positions (mm) -> (n, 2) command offsets (mm).
    x_nodes_mm, y_nodes_mm : ndarray
        Node positions along x and y (mm).
    region_mm : tuple
        ``(x_min, x_max, y_min, y_max)`` where the correction was measured.
        Nodes outside it take the value at the nearest point of the region grown
        by ``margin_mm`` (constant extrapolation: a network is not trusted far
        outside its data).
    max_extrapolated_fraction : float
        Refuse when more of the table than this lies outside the measured region.
    margin_mm : float, optional
        How far outside the region the correction itself is still evaluated, so
        that the cells straddling the region's edge interpolate it faithfully;
        default one node spacing.

    Returns
    -------
    Sampled
    """
    gx, gy = np.meshgrid(x_nodes_mm, y_nodes_mm)
    xy = np.column_stack([gx.ravel(), gy.ravel()])
    lo = np.array([region_mm[0], region_mm[2]])
    hi = np.array([region_mm[1], region_mm[3]])
    tol = 1e-9 * max(1.0, float(np.max(np.abs(xy))))
    outside = np.any((xy < lo - tol) | (xy > hi + tol), axis=1)
    frac = float(np.mean(outside))
    if frac > max_extrapolated_fraction:
        raise MarkcalError(
            f"the table's field ({x_nodes_mm[0]:.1f}..{x_nodes_mm[-1]:.1f} mm) is much larger than the measured "
            f"region ({lo[0]:.1f}..{hi[0]:.1f} x {lo[1]:.1f}..{hi[1]:.1f} mm): {frac:.0%} of the nodes would be "
            "extrapolated (check the lens field size, or allow extrapolation)")
    if margin_mm is None:
        margin_mm = float(max(np.max(np.diff(x_nodes_mm)), np.max(np.diff(y_nodes_mm))))
    d = np.asarray(offset_mm(np.clip(xy, lo - margin_mm, hi + margin_mm)), float)
    shape = gx.shape
    return Sampled(GridCorrection(np.asarray(x_nodes_mm, float), np.asarray(y_nodes_mm, float),
                                  d[:, 0].reshape(shape), d[:, 1].reshape(shape)), int(outside.sum()))


def check_interpolation(offset_mm, table: GridCorrection, region_mm: tuple, tolerance_mm: float,
                        what: str = "table") -> float:
    """Refuse a table too coarse for the correction it carries.

    Compares the table's bilinear interpolation with the correction itself at
    the cell centres inside the measured region; returns the largest
    difference (mm) and raises when it exceeds ``tolerance_mm``.
    """
    xc = 0.5 * (table.x_mm[1:] + table.x_mm[:-1])
    yc = 0.5 * (table.y_mm[1:] + table.y_mm[:-1])
    xc = xc[(xc >= region_mm[0]) & (xc <= region_mm[1])]
    yc = yc[(yc >= region_mm[2]) & (yc <= region_mm[3])]
    if not len(xc) or not len(yc):
        return 0.0
    gx, gy = np.meshgrid(xc, yc)
    xy = np.column_stack([gx.ravel(), gy.ravel()])
    err = np.hypot(*(table.offset(xy) - np.asarray(offset_mm(xy))).T)
    worst = int(np.argmax(err))
    if err[worst] > tolerance_mm:
        raise MarkcalError(
            f"{what} too coarse for this correction: between nodes its interpolation departs by "
            f"{err[worst] * 1e3:.2f} µm (more than {tolerance_mm * 1e3:.2f} µm) at "
            f"({xy[worst, 0]:.1f}, {xy[worst, 1]:.1f}) mm")
    return float(err[worst])


def check_range(values: np.ndarray, lo: float, hi: float, what: str, unit: str) -> None:
    """Refuse values a format cannot hold (no silent clipping)."""
    v = np.asarray(values)
    bad = (v < lo) | (v > hi)
    if np.any(bad):
        worst = v[bad][np.argmax(np.abs(v[bad]))]
        raise MarkcalError(f"{what}: value {worst:.0f} {unit} is outside the format's range "
                           f"{lo:.0f}..{hi:.0f} {unit} ({int(bad.sum())} entries); the correction does not fit")
