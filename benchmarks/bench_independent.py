"""Indents flow on the two independently written renderers: accuracy against their truth, beside the goals.

Usage: python benchmarks/bench_independent.py [--afm-seeds 1-12] [--afm-size 256] [--margin-every 3]
       [--pile-mode crest] [--om-seeds 1-4] [--om-sizes 1,2,3] [--om-tie-lines] [--om-size-px 480]
       (an empty seed list, e.g. --om-seeds "", skips that renderer)

AFM single imprints (fixtures/indent_single_ruled): every ``--margin-every``-th seed has a corner
3 px from the border. Goals: mean diagonal within 0.5 % or 1 px (the larger), depth 1 % (vs the
true floor), area 1 % (vs the area below the original level, markcal's definition), corners 1.5 px.
Corners are derived from indents.csv (centre, orientation_deg = direction of diagonal 1, diag1_um,
diag2_um), as the renderer's own evaluation did.

OM arrays (fixtures/indent_om_aperture, 5 x 5 at 8 µm, 0.1 µm pixels): goals every mean diagonal
within +-50 nm, centre RMS <= 10 nm, image-wide centre bias <= 10 nm.

markcal runs in-process (``run_indents``); renders go to a temporary folder. runtime_s is the
flow's own (summary.json's ``runtime_s``).
"""
from __future__ import annotations

import argparse
import itertools
import math
import os
import sys
import tempfile

import numpy as np

from markcal.fixtures.indent_om_aperture import render_om_aperture, write_om_aperture
from markcal.fixtures.indent_single_ruled import render_single_ruled, write_single_ruled
from markcal.pipeline.config import read_array_spec
from markcal.pipeline.flows.indents import IndentsOptions, run_indents

D_GOAL_PCT, D_GOAL_PX, DEPTH_GOAL_PCT, AREA_GOAL_PCT, CORNER_GOAL_PX = 0.5, 1.0, 1.0, 1.0, 1.5
OM_D_GOAL_NM, OM_RMS_GOAL_NM, OM_BIAS_GOAL_NM = 50.0, 10.0, 10.0


def parse_seeds(text):
    """``"1-4,7"`` -> [1, 2, 3, 4, 7]; empty -> []."""
    out = []
    for part in filter(None, (p.strip() for p in text.split(","))):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b) + 1)) if b else [int(a)]
    return out


def _angdiff180(a_deg, b_deg):
    d = (a_deg - b_deg) % 180.0
    return min(d, 180.0 - d)


def afm_errors(table, k, truth):
    """Errors of row ``k`` of indents.csv columns ``table`` against the single-imprint ``truth``.

    Returns
    -------
    dict
        d_err_pct, d_err_px, depth_err_pct, area_err_pct (vs area below the original level),
        area_err_footprint_pct, corner_max_px (corners derived from centre, orientation and
        diagonals, best assignment to the true corners).
    """
    px = truth["pixel_um"]
    d_true = truth["d_mean_um"]
    d = float(table["d_um"][k])
    area = float(table["area_um2"][k])
    o = math.radians(float(table["orientation_deg"][k]))
    e1 = np.array([math.cos(o), math.sin(o)])
    e2 = np.array([-math.sin(o), math.cos(o)])
    c = np.array([table["x_um"][k], table["y_um"][k]], float)
    m1, m2 = float(table["diag1_um"][k]), float(table["diag2_um"][k])
    mc = np.array([c + m1 / 2 * e1, c + m2 / 2 * e2, c - m1 / 2 * e1, c - m2 / 2 * e2])
    tc = np.array([[q["x_um"], q["y_um"]] for q in truth["corners"]])
    corner = min(float(np.max(np.hypot(*(mc[list(p)] - tc).T))) for p in itertools.permutations(range(4))) / px
    return {"d_err_pct": 100 * (d / d_true - 1), "d_err_px": (d - d_true) / px,
            "depth_err_pct": 100 * (float(table["depth_nm"][k]) / truth["depth_nm"] - 1),
            "area_err_pct": 100 * (area / truth["area_below_original_level_um2"] - 1),
            "area_err_footprint_pct": 100 * (area / truth["area_um2"] - 1),
            "corner_max_px": corner}


def afm_within(e, truth):
    """Goal flags (d, depth, area, corners) of one AFM error dict."""
    d_tol_pct = max(D_GOAL_PCT, 100 * D_GOAL_PX * truth["pixel_um"] / truth["d_mean_um"])
    return (abs(e["d_err_pct"]) <= d_tol_pct, abs(e["depth_err_pct"]) <= DEPTH_GOAL_PCT,
            abs(e["area_err_pct"]) <= AREA_GOAL_PCT, e["corner_max_px"] <= CORNER_GOAL_PX)


def nearest_row(table, x_um, y_um):
    """Index of the indents.csv row nearest (x_um, y_um)."""
    return int(np.argmin(np.hypot(np.asarray(table["x_um"]) - x_um, np.asarray(table["y_um"]) - y_um)))


def om_errors(table, truth, match_um=1.0):
    """Per-imprint errors of an OM array (nm): matched rows' d and centre errors, spurious rows.

    Each row goes to the nearest true imprint within ``match_um``; a second row on the same
    imprint is spurious. d is indents.csv's ``diameter_um`` against the true mean diagonal.
    """
    imps = truth["imprints"]
    txy = np.array([[t["x_um"], t["y_um"]] for t in imps])
    matched, spurious = {}, 0
    for x, y, dm in zip(table["x_um"], table["y_um"], table["diameter_um"]):
        dist = np.hypot(txy[:, 0] - x, txy[:, 1] - y)
        j = int(np.argmin(dist))
        if not np.isfinite(dist[j]) or dist[j] > match_um or j in matched:
            spurious += 1
            continue
        matched[j] = (1e3 * (dm - imps[j]["d_um"]), 1e3 * (x - txy[j, 0]), 1e3 * (y - txy[j, 1]))
    e = np.array(list(matched.values())).reshape(-1, 3)
    return e, len(imps), spurious


def om_stats(e, n_true):
    """Mean and max |d error|, fraction within the goal (of all true imprints), centre RMS, bias (nm)."""
    if not len(e):
        return dict(mean_d=np.nan, max_d=np.nan, within=0.0, rms=np.nan, bias=np.nan)
    bias = e[:, 1:].mean(axis=0)
    return dict(mean_d=float(np.mean(e[:, 0])), max_d=float(np.max(np.abs(e[:, 0]))),
                within=float(np.sum(np.abs(e[:, 0]) <= OM_D_GOAL_NM)) / n_true,
                rms=float(np.sqrt(np.mean(np.sum(e[:, 1:] ** 2, axis=1)))), bias=float(np.hypot(*bias)))


def afm_sweep(a, tmp):
    seeds = parse_seeds(a.afm_seeds)
    print(f"AFM single imprints (fixtures/indent_single_ruled), seeds {a.afm_seeds}, {a.afm_size} x {a.afm_size}, "
          f"pile-up {a.pile_mode}; seeds divisible by {a.margin_every}: a corner {a.margin_px:g} px from the border")
    print(f"goals: d {D_GOAL_PCT} % or {D_GOAL_PX:g} px (larger), depth {DEPTH_GOAL_PCT:g} % (true floor), "
          f"area {AREA_GOAL_PCT:g} % (below original level), corners {CORNER_GOAL_PX} px")
    print("seed pix_nm   d_um fill    bow pile%  margin   d_err%  d_px  depth%  area%z0  area%fp  corner_px  "
          "n  runtime_s  fails")
    rows, ok = [], []
    for s in seeds:
        margin = a.margin_px if a.margin_every and s % a.margin_every == 0 else None
        r = render_single_ruled(s, size_px=a.afm_size, corner_margin_px=margin, pile_mode=a.pile_mode)
        t = r.truth
        gsf, _ = write_single_ruled(r, tmp, f"afm_seed{s:03d}")
        res = run_indents([gsf], None, IndentsOptions(load_mN=500.0))
        k = nearest_row(res.indents, *t["centre_um"])
        e = afm_errors(res.indents, k, t)
        flags = afm_within(e, t)
        rows.append(e)
        ok.append(flags)
        fails = ",".join(n for n, f in zip(("d", "depth", "area", "corners"), flags) if not f)
        print(f"{s:4d} {t['pixel_nm']:6.1f} {t['d_mean_um']:6.2f} {t['fill_linear']:.2f} {t['bow_mean']:+.3f} "
              f"{100 * t['pile_frac']:5.1f} {'-' if margin is None else f'{margin:g}':>7} "
              f"{e['d_err_pct']:+7.2f} {e['d_err_px']:+5.2f} {e['depth_err_pct']:+7.2f} {e['area_err_pct']:+8.2f} "
              f"{e['area_err_footprint_pct']:+8.2f} {e['corner_max_px']:10.2f} {len(res.indents['x_um']):2d} "
              f"{res.summary['runtime_s']:10.3f}  {fails}", flush=True)
    if not rows:
        return
    mx = {k: max(abs(e[k]) for e in rows) for k in rows[0]}
    frac = np.mean(np.array(ok, float), axis=0)
    print(f"all {len(rows)}: max |d| {mx['d_err_pct']:.2f} % ({mx['d_err_px']:.2f} px), |depth| "
          f"{mx['depth_err_pct']:.2f} %, |area| {mx['area_err_pct']:.2f} % (vs footprint "
          f"{mx['area_err_footprint_pct']:.2f} %), corners {mx['corner_max_px']:.2f} px; within goal: d "
          f"{100 * frac[0]:.0f} %, depth {100 * frac[1]:.0f} %, area {100 * frac[2]:.0f} %, corners "
          f"{100 * frac[3]:.0f} %; all four {100 * np.mean(np.all(ok, axis=1)):.0f} %")


def om_sweep(a, tmp):
    seeds = parse_seeds(a.om_seeds)
    sizes = [float(v) for v in a.om_sizes.split(",") if v.strip()]
    print(f"\nOM arrays (fixtures/indent_om_aperture), seeds {a.om_seeds}, sizes {a.om_sizes} µm, "
          f"{a.om_size_px} px at {a.om_pixel_um} µm, tie_lines={a.om_tie_lines}")
    print(f"goals: every d within +-{OM_D_GOAL_NM:g} nm, centre RMS <= {OM_RMS_GOAL_NM:g} nm, "
          f"bias <= {OM_BIAS_GOAL_NM:g} nm")
    print("seed  d_um  found  mean_dE_nm  max|dE|_nm  in+-50  c_rms_nm  bias_nm  runtime_s  fails")
    allv, n_true_all, n_ok, n_img = [], 0, 0, 0
    for d in sizes:
        for s in seeds:
            r = render_om_aperture(s, d, size_px=a.om_size_px, pixel_um=a.om_pixel_um, tie_lines=a.om_tie_lines)
            tif, toml = write_om_aperture(r, tmp, f"om_s{s}_d{d:g}")
            res = run_indents([tif], read_array_spec(toml))
            e, n_true, spurious = om_errors(res.indents, r.truth)
            st = om_stats(e, n_true)
            fails = [n for n, bad in (("found", len(e) < n_true), ("d", st["within"] < 1.0),
                                      ("rms", not st["rms"] <= OM_RMS_GOAL_NM),
                                      ("bias", not st["bias"] <= OM_BIAS_GOAL_NM)) if bad]
            n_img += 1
            n_ok += not fails
            allv.append(e)
            n_true_all += n_true
            print(f"{s:4d} {d:5g} {len(e):3d}/{n_true} {st['mean_d']:+11.1f} {st['max_d']:11.1f} "
                  f"{100 * st['within']:6.0f}% {st['rms']:9.1f} {st['bias']:8.1f} {res.summary['runtime_s']:10.2f}  "
                  f"{','.join(fails)}" + (f" spurious={spurious}" if spurious else ""), flush=True)
    if not n_img:
        return
    e = np.vstack(allv)
    print(f"all {n_img} images: found {len(e)}/{n_true_all}, max |d error| {np.max(np.abs(e[:, 0])):.1f} nm, "
          f"{100 * np.sum(np.abs(e[:, 0]) <= OM_D_GOAL_NM) / n_true_all:.0f} % within +-{OM_D_GOAL_NM:g} nm; "
          f"images meeting every goal {n_ok}/{n_img}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--afm-seeds", default="1-12", help='e.g. "1-12" or "1,5,9"; "" skips')
    ap.add_argument("--afm-size", type=int, default=256)
    ap.add_argument("--margin-every", type=int, default=3, help="every n-th seed: a corner near the border (0: none)")
    ap.add_argument("--margin-px", type=float, default=3.0)
    ap.add_argument("--pile-mode", default="crest", choices=["crest", "base"])
    ap.add_argument("--om-seeds", default="1-4", help='"" skips')
    ap.add_argument("--om-sizes", default="1,2,3", help="nominal diagonals (µm)")
    ap.add_argument("--om-tie-lines", action="store_true", help="edge lines with the ridge lines' depth and width")
    ap.add_argument("--om-size-px", type=int, default=480)
    ap.add_argument("--om-pixel-um", type=float, default=0.1)
    a = ap.parse_args(argv)
    print(f"load average {' '.join(f'{v:.1f}' for v in os.getloadavg())} at start", file=sys.stderr)
    with tempfile.TemporaryDirectory(prefix="bench_independent_") as tmp:
        if parse_seeds(a.afm_seeds):
            afm_sweep(a, tmp)
        if parse_seeds(a.om_seeds):
            om_sweep(a, tmp)


if __name__ == "__main__":
    main()
