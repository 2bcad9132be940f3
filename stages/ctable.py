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

__all__ = ["Sampled", "sample_onto_nodes", "check_interpolation", "check_range", "centred_nodes",
           "ComponentStructure", "TableStructure", "table_structure"]


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
    v = np.asarray(values, float)
    if not np.all(np.isfinite(v)):
        raise MarkcalError(f"{what}: {int((~np.isfinite(v)).sum())} entries are not finite (NaN or infinite): "
                           "the correction is broken; nothing written")
    bad = (v < lo) | (v > hi)
    if np.any(bad):
        worst = v[bad][np.argmax(np.abs(v[bad]))]
        raise MarkcalError(f"{what}: value {worst:.0f} {unit} is outside the format's range "
                           f"{lo:.0f}..{hi:.0f} {unit} ({int(bad.sum())} entries); the correction does not fit")


# ----------------------------------------------------------------------------- structure of a stored table

#: how clear the evidence must be (of 2) before a layout is named
LAYOUT_EVIDENCE_MIN = 0.5


@dataclass(frozen=True)
class ComponentStructure:
    """Symmetry of one stored component (file order ``[outer, inner]``).

    Attributes
    ----------
    odd_inner, odd_outer : float
        Antisymmetry about the centre node along the inner / outer index,
        ``-sum(v * mirror(v)) / sum(v**2)`` of the values minus the centre node:
        1 for an odd component (zero on the middle line, opposite signs at the
        two ends), -1 for an even one, near 0 for no symmetry.
    centre : float
        Value at the centre node (file units).
    middle_inner_max, middle_outer_max : float
        Largest ``|value - centre|`` on the middle line where the inner (outer)
        index is at the centre: 0 for a component exactly odd along it.
    rms : float
        RMS of the values minus the centre node (file units).
    """

    odd_inner: float
    odd_outer: float
    centre: float
    middle_inner_max: float
    middle_outer_max: float
    rms: float


@dataclass(frozen=True)
class TableStructure:
    """Which index each component of a stored table is odd along.

    Attributes
    ----------
    first, second : ComponentStructure
        The first and second value of each pair (``.cor``), or the X and Y
        table (``.ctb``), or the x and y columns (text formats).
    first_along : {"inner", "outer", "none"}
        The index the first component's axis runs along, judged from both
        components (an x correction is odd in x, a y correction odd in y);
        ``none``: the table fits no known layout (see ``reason``).
    evidence : float
        -2..2; positive for "inner", negative for "outer".
    reason : str
        Why no layout was named ("" when one was).
    """

    first: ComponentStructure
    second: ComponentStructure
    first_along: str
    evidence: float
    reason: str


def _component(v: np.ndarray) -> ComponentStructure:
    c0, c1 = v.shape[0] // 2, v.shape[1] // 2
    d = np.asarray(v, float) - float(v[c0, c1])
    e = float(np.sum(d * d))
    odd_in = -float(np.sum(d * d[:, ::-1])) / e if e > 0 else 0.0
    odd_out = -float(np.sum(d * d[::-1, :])) / e if e > 0 else 0.0
    return ComponentStructure(odd_in, odd_out, float(v[c0, c1]), float(np.max(np.abs(d[:, c1]))),
                              float(np.max(np.abs(d[c0, :]))), float(np.sqrt(e / d.size)))


def table_structure(first: np.ndarray, second: np.ndarray) -> TableStructure:
    """Symmetry of a stored two-component table and the layout it fits.

    Parameters
    ----------
    first, second : ndarray
        (n_outer, n_inner) components in file order, odd counts (a centre node).

    Returns
    -------
    TableStructure
        ``first_along`` is ``inner`` when the first component is odd along the
        inner index and the second along the outer one (EZCAD's and SCANLAB's
        files), ``outer`` for the transposed layout, ``none`` when the table has
        no such structure (all zero, constant, permuted, or the two components
        odd along the same index). A table dominated by a rotation or shear
        (no scale or lens term) cannot show its layout and may be misjudged.
    """
    first, second = np.asarray(first, float), np.asarray(second, float)
    if first.shape != second.shape or first.ndim != 2 or first.shape[0] % 2 == 0 or first.shape[1] % 2 == 0:
        raise MarkcalError(f"a table's two components need the same odd shape (got {first.shape}, {second.shape})")
    a, b = _component(first), _component(second)
    wa, wb = a.rms ** 2, b.rms ** 2
    if wa + wb == 0:
        nonzero = np.any(first != 0) or np.any(second != 0)
        return TableStructure(a, b, "none", 0.0, "every entry equals the centre node's" if nonzero
                              else "every entry is zero")
    ev = (wa * (a.odd_inner - a.odd_outer) + wb * (b.odd_outer - b.odd_inner)) / (wa + wb)
    if ev >= LAYOUT_EVIDENCE_MIN:
        return TableStructure(a, b, "inner", ev, "")
    if ev <= -LAYOUT_EVIDENCE_MIN:
        return TableStructure(a, b, "outer", ev, "")
    return TableStructure(a, b, "none", ev, f"neither component is clearly odd along one index and the other along "
                                            f"the other (evidence {ev:+.2f}; a layout needs |evidence| >= "
                                            f"{LAYOUT_EVIDENCE_MIN})")
