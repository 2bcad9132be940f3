"""The level each corner is carried to, against the true surface's level, on the scanner renderer's four-edge seeds.

Usage: python benchmarks/bench_corner_levels.py [--seeds 1-40]

Where pile-up stands on all four edges (fixtures/indent_afm_scanner), the leveller's far field lies on the lobes' tails
and the levelled map's zero above the surface, and each corner is carried to the level :func:`level_beyond` finds
beyond it (the window's median, or the bottom of the crease between the lobes). Each seed is drawn twice with the
same instrument: as it is, and without pile-up and cracks. The leveller's correction (the map minus the levelled map)
taken from the first and applied to the second gives the true surface's level in the levelled map, along each true
corner's diagonal 4-14 px beyond it. Printed per corner: that level, and the errors (nm) of the crease's bottom and of
the level taken. Square pixels (``nonsquare=False``), so that a corner's pixel is its position over the pixel size.
"""
from __future__ import annotations

import argparse

import numpy as np
from scipy import ndimage

from markcal.fixtures.indent_afm_scanner import FACE_DEG, render_scanner
from markcal.stages.indent_corners import crease_beyond, level_beyond
from markcal.stages.indent_level import level_map

from bench_independent import parse_seeds  # noqa: E402  (benchmarks/ is the script's folder)

def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1-40")
    a = ap.parse_args(argv)
    print("seed corner crack  true_nm | crease_err_nm  level_err_nm  level_err_px  slope_nm_px")
    err_px = []
    for s in parse_seeds(a.seeds):
        r = render_scanner(s, 256, nonsquare=False)
        tr, px = r.truth, r.pixel_um[0]
        if len(tr["pileup"]["edges"]) < 4:
            continue
        bare = render_scanner(s, 256, nonsquare=False, pileup=False, cracks=False)
        raw = 1e9 * np.asarray(r.layers["HeightTrace"], float)
        lv, _ = level_map(raw, px)
        surface = 1e9 * np.asarray(bare.layers["HeightTrace"], float) - (raw - lv.z_nm)
        zc = ndimage.spline_filter(np.nan_to_num(lv.z_nm), order=3, mode="nearest")
        slope = np.tan(np.radians(FACE_DEG)) * px * 1000.0           # the facets' slope (nm per px), as drawn
        centre = np.array(tr["centre_um"])[::-1] / px
        for k, q in enumerate(np.array(tr["corners_um"])):
            rc = q[::-1] / px
            e = (rc - centre) / np.hypot(*(rc - centre))
            pts = rc[None] + np.arange(4.0, 14.01, 0.5)[:, None] * e
            ok = (pts >= 0).all(axis=1) & (pts <= np.array(raw.shape) - 1).all(axis=1)
            if ok.sum() < 8:
                continue
            true_nm = float(np.median(ndimage.map_coordinates(surface, pts[ok].T, order=1)))
            level = level_beyond(zc, lv.z_nm, rc, e, slope, lv.noise_nm)
            crease = crease_beyond(zc, rc, e, slope, lv.noise_nm)
            crack = any(c["corner"] == k for c in tr["cracks"])
            err_px.append((level - true_nm) / slope)
            ce = "        -" if crease is None else f"{crease[0] - true_nm:+9.1f}"
            print(f"{s:4d} {k:6d} {'yes' if crack else 'no':>5s} {true_nm:8.1f} | {ce:>13s} {level - true_nm:+13.1f} "
                  f"{err_px[-1]:+13.2f} {slope:12.1f}", flush=True)
    v = np.array(err_px)
    if v.size:
        print(f"{v.size} corners: level error median {np.median(v):+.2f} px, mean |error| {np.abs(v).mean():.2f} px, "
              f"max |error| {np.abs(v).max():.2f} px, over 0.5 px {int((np.abs(v) > 0.5).sum())}")


if __name__ == "__main__":
    main()
