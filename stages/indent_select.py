"""The measurement decisions of the indents flow, as stages: which imprints count, and tolerance flags.

- :func:`merge_afm`: one AFM imprint from the facet model and the single-imprint metrology;
- :func:`accept_imprints`: depth floor, size window, duplicates;
- :func:`tolerance_flags`: diameter within tolerance of the nominal and H/D above its minimum;
- :func:`mixed_spots`, :func:`one_size`: whether a micrograph's dark dots are imprints of one load at all;
- :func:`raised_and_sunk_um3`: whether an AFM map's features stand up rather than lie down (inverted heights).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from . import detect
from .cv_filters import gaussian
from .indent_geometry import Imprint

__all__ = ["LARGE_IMPRINT_PX", "rounding_px", "merge_afm", "accept_imprints", "dedupe", "tolerance_flags",
           "mixed_spots", "one_size", "raised_and_sunk_um3"]

#: from this mean diagonal (px) on, corners come from the contact boundary (extreme points on
#: bowed edges); below it the facet model's corners are the better estimate
LARGE_IMPRINT_PX = 40.0


def rounding_px(facet: Imprint, pixel_um: float) -> float:
    """Width (px) of the facet model's rounded apex: blend (nm) / facet slope.

    Under a pixel, the pixels do not sample the floor (the lowest pixel lies up to a slope
    times half a pixel above it) and the model's floor is the better depth; from a pixel on,
    the measured floor is.
    """
    slope = facet.depth_nm / (500.0 * facet.diameter_um)
    if not (np.isfinite(facet.blend_nm) and slope > 0):
        return 0.0
    return float(facet.blend_nm / slope / 1000.0 / pixel_um)


def merge_afm(facet: Imprint | None, single, pixel_um: float) -> Imprint | None:
    """One AFM imprint record from the facet-model fit and the single-imprint metrology.

    Large imprints (mean diagonal >= ``LARGE_IMPRINT_PX``) or ones the facet model cannot
    fit take centre, corners, diagonals and depth (the measured floor) from ``single``; small
    ones keep the facet model's centre, corners and diagonals, and their ``depth_nm`` is the
    measured floor where the apex rounding is at least a pixel wide (:func:`rounding_px`; else
    the facet model's floor, which the pixels do not sample). Area, pile-up volume, edge bow and the border flag always
    come from ``single``; ``apex_depth_nm`` is the facet model's depth.

    Parameters
    ----------
    facet : Imprint or None
        From ``indent_afm.measure_afm``.
    single : SingleImprint or None
        From ``indent_single.measure_single``.
    """
    if single is None:
        return facet
    nan = float("nan")
    extra = dict(area_um2=single.area_um2, pileup_volume_um3=single.pileup_volume_um3,
                 edge_bow=float(np.nanmean(single.edge_bow)) if np.isfinite(single.edge_bow).any() else nan,
                 cut_by_border=bool(single.cut_by_border), contour_um=single.contour_um, floor_um=single.floor_um,
                 apex_depth_nm=facet.depth_nm if facet is not None else nan, floor_share=single.floor_share,
                 half_share=single.half_share,
                 chipped_area_um2=single.chipped_area_um2, chips_um=single.chips_um)
    if facet is not None and single.d_um / pixel_um < LARGE_IMPRINT_PX:
        if np.isfinite(single.depth_nm) and rounding_px(facet, pixel_um) >= 1.0:
            # the rounded floor is resolved by the pixels: depth to the measured floor (the lowest
            # point of the denoised surface), not the facet model's extrapolated blend
            extra.update(depth_nm=single.depth_nm, hd_ratio=float(single.depth_nm / (1000 * facet.diameter_um)))
        return dataclasses.replace(facet, **extra)
    hd = single.depth_nm / (1000 * single.diameter_um)
    return Imprint(x_um=single.x_um, y_um=single.y_um, diameter_um=single.diameter_um, diag1_um=single.diag1_um,
                   diag2_um=single.diag2_um, depth_nm=single.depth_nm, hd_ratio=float(hd),
                   orientation_deg=single.orientation_deg, pileup_nm=single.pileup_nm,
                   corners_um=single.corners_um, fit_rms=facet.fit_rms if facet is not None else nan,
                   n_pixels=single.n_pixels, blend_nm=facet.blend_nm if facet is not None else nan, **extra)


def dedupe(imps: list) -> list:
    """Keep one of imprints closer than half a diameter (the one with more pixels), most pixels first."""
    if not imps:
        return []
    kept = set(detect.dedupe([[m.x_um, m.y_um] for m in imps], [m.n_pixels for m in imps],
                             0.5 * np.array([m.diameter_um for m in imps], float)).tolist())
    return [imps[i] for i in sorted(range(len(imps)), key=lambda i: -imps[i].n_pixels) if i in kept]


MIN_IMPRINT_HD = 0.02       # depth / diameter under which a pit is not an imprint (Vickers: 0.14 sharp)
MAX_FLOOR_SHARE = 0.085     # share of a pit deeper than 80 % of its depth above which it is flat-bottomed ...
MAX_PYRAMID_HALF_SHARE = 0.40   # ... unless under this share lies deeper than half its depth (a pyramid: 0.25)


def _flat_bottomed(m) -> bool:
    """A flat-bottomed pit (a calibration grating's), not a pyramid: over ``MAX_FLOOR_SHARE`` of it deeper than 80 %
    of its depth, and (where the model-free measurement gives it) over ``MAX_PYRAMID_HALF_SHARE`` deeper than half.

    A pyramid's deepest fifth holds 3-7 % of it on every renderer (blunted, rounded, recovered), the square pits of
    the real grating ``grid1.nid`` 9.5-28 %. But the mean of trace and retrace flattens a V floor: 8.5-10 % on 6 of 60
    feedback-renderer maps aligned first, up to 16 % unaligned, and they were refused as `no imprint found`. Deeper
    than half the depth: a pyramid 0.25 (0.08-0.38 over those renderers and averages), the grating's pits with a flat
    floor 0.43-0.74 (the real ``circles.nid``'s 0.33-0.73; those under 0.40 are refused as too shallow, H/D < 0.003).
    """
    return bool(m.floor_share > MAX_FLOOR_SHARE and not m.half_share <= MAX_PYRAMID_HALF_SHARE)


#: pixels sharing a map's lowest height exactly, from which its floor is taken as clipped (the Z range's end)
MIN_CLIPPED_PX = 8


def clipped_floor(z_nm: np.ndarray) -> np.ndarray | None:
    """The pixels holding exactly the map's lowest height (bool, the map's shape) when there are ``MIN_CLIPPED_PX``
    or more, else None.

    A scanner at the end of its Z range reads one value wherever the surface lies deeper: the floor of an
    imprint deeper than the range becomes a plateau of equal heights. A scanned floor has noise (even a
    16-bit file's rounding leaves a pyramid's blunted floor one or two pixels within a step).
    """
    z = np.asarray(z_nm)
    fin = np.isfinite(z)
    if not fin.any():
        return None
    low = fin & (z == z[fin].min())
    return low if np.count_nonzero(low) >= MIN_CLIPPED_PX else None


def accept_imprints(imps: list, pixel_um: float, min_depth_nm: float | None = None,
                    size_window_um: tuple | None = None, floor_clipped: bool = False) -> list:
    """Imprints that count: measured, deeper than ``min_depth_nm`` (AFM), wider than 3 px,
    inside ``size_window_um`` (lo, hi) of the diameter when given, duplicates removed.

    Without a size window (no array spec), an AFM pit shallower than ``MIN_IMPRINT_HD`` of its diameter
    is not an imprint: a Vickers imprint's H/D is 0.14, 0.07-0.1 after the elastic recovery of glass. Line
    offsets of a few nm had made 0.7 µm "imprints" 11 nm deep (H/D 0.016) beside a real one. With a spec,
    shallow imprints of the array stay, to be counted by the H/D check. Nor, without a size window, is a
    flat-bottomed pit (:func:`_flat_bottomed`);
    nor a pit under ``LARGE_IMPRINT_PX`` that the four-facet model could not fit (the one grating pit of
    4.5 %); nor a pit whose contact area is far from that of the quadrilateral between its corners
    (``AREA_RATIO_RANGE``). A ``floor_clipped`` map (:func:`clipped_floor`) is flat at its floor
    because the scanner could not go deeper: the flat-bottom test does not apply there.
    """
    out = [m for m in imps if m is not None and m.diameter_um > 3 * pixel_um]
    if min_depth_nm is not None:
        out = [m for m in out if m.depth_nm > min_depth_nm]
        if size_window_um is None:
            out = [m for m in out if not (m.depth_nm < MIN_IMPRINT_HD * m.diameter_um * 1e3
                                          or (_flat_bottomed(m) and not floor_clipped)
                                          or _no_pyramid(m, pixel_um)
                                          or _no_quadrilateral(m))]
    if size_window_um is not None:
        lo, hi = size_window_um
        out = [m for m in out if lo <= m.diameter_um <= hi]
    return dedupe(out)


#: contact area / (d^2 / 2) of an AFM imprint. Measured on every imprint of five renderers (ruled
#: independent seeds 1-40, ours 2000-2019, the feedback renderer 1-20 with and without chips, arrays and
#: rounded arrays): 0.76-1.22 (bowed edges of 8 % of d/2 make +-15 %). The pits beside the pile-up lobes of a
#: map whose heights are inverted: 1.6-3.7 or 0.2 (they had been reported as imprints of half the size).
AREA_RATIO_RANGE = (0.6, 1.4)


def _no_quadrilateral(m) -> bool:
    """True for an AFM pit whose contact area is outside ``AREA_RATIO_RANGE`` of d^2 / 2 (NaN: no judgement).

    The area as the boundary encloses it, chips included (the range was measured so; a pit that is no
    imprint is not made one by its edges drawn past what sticks out of them).
    """
    ratio = (m.area_um2 + np.nan_to_num(m.chipped_area_um2)) / (0.5 * m.d_um ** 2)
    return bool(np.isfinite(ratio) and not AREA_RATIO_RANGE[0] <= ratio <= AREA_RATIO_RANGE[1])


def _no_pyramid(m, pixel_um) -> bool:
    """True for an AFM pit small enough for the facet model (under ``LARGE_IMPRINT_PX``) that it did not fit."""
    return not np.isfinite(m.fit_rms) and 0.5 * (m.diag1_um + m.diag2_um) / pixel_um < LARGE_IMPRINT_PX


#: Without an array spec, a micrograph's dots are imprints of one load only when most share a size. Measured
#: (no spec, the flow's dot fit): OM arrays of 1-3 µm on three renderers, dust included, 96-100 % of the dots
#: within 20 % of the median diagonal; the grain specks of a BSE image 48 %.
MIN_ONE_SIZE_SHARE = 0.75
ONE_SIZE_TOLERANCE = 0.2
#: dark spots found before the fit whose 90th/10th percentile radius is above this are grain or dust
#: rather than an array (OM arrays with dust 1.03-1.34; BSE grain 1.77-2.16 on whole images, 1.5-3.4 on crops)
MIXED_SPOTS_RATIO = 1.5


def mixed_spots(radii_px) -> bool:
    """True when a micrograph's dark spots (:func:`detect_dots` radii, px) come in every size: grain or dust."""
    r = np.asarray(radii_px, float)
    if len(r) < 5:
        return False
    p10, p90 = np.percentile(r, [10, 90])
    return bool(p90 > MIXED_SPOTS_RATIO * p10)


def one_size(imps: list) -> bool:
    """True when at least ``MIN_ONE_SIZE_SHARE`` of the imprints lie within ``ONE_SIZE_TOLERANCE`` of the
    median diagonal (always for fewer than 5)."""
    if len(imps) < 5:
        return True
    d = np.array([m.d_um for m in imps])
    return bool(np.mean(np.abs(d / np.median(d) - 1) <= ONE_SIZE_TOLERANCE) >= MIN_ONE_SIZE_SHARE)


def raised_and_sunk_um3(z_nm: np.ndarray, noise_nm: float, pixel_um: float) -> tuple:
    """Volumes (µm³) standing above and lying below a levelled map's surface, beyond 5 noise levels (smoothed by
    1 px).

    Imprints are pits: measured on four renderers (single imprints and arrays, 39 maps) what stands up (pile-up)
    is 0.04-0.44 of what lies down; with the heights negated, 2.3-25 times it.
    """
    zs = gaussian(np.nan_to_num(np.asarray(z_nm, np.float32)), 1.0)
    t = 5.0 * noise_nm
    up, down = zs[zs > t], zs[zs < -t]
    scale = pixel_um * pixel_um * 1e-3
    return (float(np.sum(up, dtype=np.float64) - t * up.size) * scale,
            float(-np.sum(down, dtype=np.float64) - t * down.size) * scale)


def tolerance_flags(diameter_um, nominal_um, hd, tolerance_um: float, min_hd: float) -> np.ndarray:
    """1 where |diameter - nominal| <= tolerance and H/D (when measured) >= ``min_hd``, else 0."""
    err = np.abs(np.asarray(diameter_um, float) - nominal_um)
    hd = np.asarray(hd, float)
    return ((err <= tolerance_um) & ~(np.isfinite(hd) & (hd < min_hd))).astype(int)
