"""Single imprints of the independent ruled renderer as real files come: flattened line by line, lines left
out, a floor clipped by the Z range, fewer lines than points, more noise.

Usage: python benchmarks/bench_conventions.py [--seeds 1-12] [--cases flatten-mean,nan-lines,...]

Each seed of ``fixtures/indent_single_ruled`` (every third with a corner 3 px from the border) is changed as
the case says, written as GSF and measured with ``run_indents``; the row nearest the true centre is compared
with the truth. Goals as for the other single renders: d within 0.5 % or 1 px, depth 1 %, area 1 %, corners
1.5 px (px: the render's pixel; with lines dropped, the coarser pixel is not taken into account here).
Cases:

- ``flatten-mean``, ``flatten-median``, ``flatten-line``, ``flatten-quadratic``, ``flatten-cubic``: each row's
  fit taken off; ``flatten-col-mean``, ``flatten-col-line``: each column's;
- ``nan-lines``: three lines NaN, one through the imprint's centre; ``nan-block``: 25 x 25 px NaN in a corner;
- ``clip``: heights below the map's 0.2 % percentile read as that value (the depth goal cannot be met: the
  floor is cut; the file must be flagged, ``clipped`` column);
- ``half-lines``, ``third-lines``: every second / third line only, over the same field (non-square pixels);
- ``noise5``: 5 nm white noise added;
- ``flatten-line-text3``: each row's line taken off, written as Gwyddion's ASCII data matrix to 3 significant
  digits (the flatten and its order must be found through the rounding).
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

import numpy as np

from markcal.fixtures.indent_single_ruled import render_single_ruled
from markcal.fixtures.line_flatten import flatten_lines
from markcal.pipeline.flows.indents import IndentsOptions, run_indents
from markcal.stages.errors import MarkcalError
from markcal.stages.image_io import gsf_bytes
from markcal.stages.text_maps import text_matrix

from bench_independent import afm_errors, afm_within, nearest_row, parse_seeds  # noqa: E402

CASES = ("flatten-mean", "flatten-median", "flatten-line", "flatten-quadratic", "flatten-cubic",
         "flatten-col-mean", "flatten-col-line", "nan-lines", "nan-block", "clip", "half-lines", "third-lines",
         "noise5", "flatten-line-text3")


def changed(case, r, rng):
    """The render's heights (nm) as the case changes them, and the lines' spacing over the pixel's."""
    z = r.height_nm.astype(float).copy()
    order = {"mean": 0, "line": 1, "quadratic": 2, "cubic": 3, "median": "median"}
    if case == "flatten-line-text3":                 # written below as a Gwyddion text export, 3 digits
        return flatten_lines(z, 1), 1
    if case.startswith("flatten-col-"):
        return flatten_lines(z, order[case[12:]], axis=1), 1
    if case.startswith("flatten-"):
        return flatten_lines(z, order[case[8:]]), 1
    if case == "nan-lines":
        ci = int(r.truth["centre_um"][1] / r.pixel_um)
        z[[10, ci, min(ci + 40, z.shape[0] - 6)], :] = np.nan
    elif case == "nan-block":
        z[:25, :25] = np.nan
    elif case == "clip":
        z = np.maximum(z, np.percentile(z, 0.2))
    elif case == "half-lines":
        return z[::2], 2
    elif case == "third-lines":
        return z[::3], 3
    elif case == "noise5":
        z = z + rng.normal(0.0, 5.0, z.shape)
    return z, 1


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1-12", help='e.g. "1-12" or "1,5,9"')
    ap.add_argument("--cases", default=",".join(CASES), help="comma-separated, of: " + ", ".join(CASES))
    a = ap.parse_args(argv)
    seeds, cases = parse_seeds(a.seeds), [c for c in a.cases.split(",") if c]
    bad = [c for c in cases if c not in CASES]
    if bad:
        ap.error(f"unknown case(s): {', '.join(bad)}")
    rng = np.random.default_rng(0)
    print("indent_single_ruled, 256 x 256; goals: d 0.5 % or 1 px, depth 1 %, area 1 %, corners 1.5 px")
    print("case               seed   d_err%  depth%   area%  corner_px  n  flatten/clipped/resampled    run_s")
    with tempfile.TemporaryDirectory(prefix="bench_conventions_") as tmp:
        for case in cases:
            ok = []
            for s in seeds:
                r = render_single_ruled(s, corner_margin_px=3.0 if s % 3 == 0 else None)
                z, step = changed(case, r, rng)
                field_m = z.shape[1] * r.pixel_um * 1e-6
                path = os.path.join(tmp, f"{case}_{s}.gsf")
                if case.endswith("-text3"):
                    path = path[:-4] + ".txt"
                    with open(path, "w", encoding="utf-8") as fh:
                        fh.write(text_matrix(z * 1e-9, field_m, z.shape[0] * step * r.pixel_um * 1e-6, digits=3))
                else:
                    with open(path, "wb") as fh:
                        fh.write(gsf_bytes(z * 1e-9, field_m, z.shape[0] * step * r.pixel_um * 1e-6))
                t0 = time.perf_counter()
                try:
                    res = run_indents([path], None, IndentsOptions())
                except MarkcalError as exc:
                    ok.append(False)
                    print(f"{case:18s} {s:4d}  FAILED: {exc}", flush=True)
                    continue
                t = res.indents
                k = nearest_row(t, *r.truth["centre_um"])
                e = afm_errors(t, k, r.truth)
                flags = afm_within(e, r.truth)
                ok.append(all(flags))
                info = res.files[0].info
                what = "/".join(["flat" if info.get("line_flatten") else "-",
                                 "clip" if info.get("floor_clipped_px") else "-",
                                 "resampled" if info.get("resampled") else "-"])
                print(f"{case:18s} {s:4d} {e['d_err_pct']:+8.2f} {e['depth_err_pct']:+7.2f} {e['area_err_pct']:+7.2f} "
                      f"{e['corner_max_px']:10.2f} {len(t['x_um']):2d}  {what:27s} {time.perf_counter() - t0:6.2f}",
                      flush=True)
            print(f"{case}: all four goals met on {sum(ok)} of {len(ok)}", flush=True)


if __name__ == "__main__":
    sys.exit(main())
