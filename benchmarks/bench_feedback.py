"""Indents flow on the feedback-loop AFM renderer (fixtures/indent_afm_feedback): accuracy against its truth.

Usage: python benchmarks/bench_feedback.py [--seeds 1-20] [--size 256] [--ablate NAME]

Each seed is rendered (every fourth seed has a corner 3-4 px from the border), written as GSF
into a temporary folder and measured in-process with ``run_indents``; the row nearest the
true centre is compared with the truth. Goals: mean diagonal within 0.5 % or 1 px (the larger),
depth within 1 %, area within 1 %, corners within 1.5 px. Corners are derived from the table's
centre, orientation_deg (direction of diagonal 1), diag1_um and diag2_um, with the best
assignment to the true corners. border% is the depth against a border-plane reading of the map
(``border_plane_depth_nm``; the issue's real-map goal: within 10 %). ``--ablate`` switches one artefact family off (chipping,
feedback, particles, faults, scanner; ``all``: every family off, the tip stays). run_s is the wall time of run_indents.
With ``--format ibw`` the last line compares the z loop's lag the flow took out (summary.json ``scan_lag_px``) with
the renderer's ramp lag.
"""
from __future__ import annotations

import argparse
import itertools
import math
import sys
import tempfile
import time

import numpy as np

from markcal.fixtures.indent_afm_feedback import render_feedback, write_feedback
from markcal.fixtures.indent_maps import border_plane_depth_nm
from markcal.pipeline.flows.indents import IndentsOptions, run_indents
from markcal.stages.errors import MarkcalError

from bench_independent import parse_seeds  # noqa: E402  (benchmarks/ is the script's folder)

D_GOAL_PCT, D_GOAL_PX, DEPTH_GOAL_PCT, AREA_GOAL_PCT, CORNER_GOAL_PX = 0.5, 1.0, 1.0, 1.0, 1.5
FAMILIES = ("chipping", "feedback", "particles", "faults", "scanner")
GOALS = ("d", "depth", "area", "corners")


def table_corners(t, k):
    """Four corners (x, y) of row ``k`` from centre, orientation and the two diagonals."""
    o = math.radians(float(t["orientation_deg"][k]))
    e1, e2 = np.array([math.cos(o), math.sin(o)]), np.array([-math.sin(o), math.cos(o)])
    c = np.array([t["x_um"][k], t["y_um"][k]], float)
    h1, h2 = float(t["diag1_um"][k]) / 2, float(t["diag2_um"][k]) / 2
    return np.array([c + h1 * e1, c + h2 * e2, c - h1 * e1, c - h2 * e2])


def errors(t, k, truth):
    """Errors of row ``k`` of the indents table ``t`` against ``truth``.

    Returns
    -------
    dict
        d_pct, d_px, depth_pct, area_pct, corner_px (max over the four, best assignment).
    """
    px = truth["pixel_um"]
    d = float(t["d_um"][k])
    mc, tc = table_corners(t, k), np.array(truth["corners_um"])
    corner = min(float(np.max(np.hypot(*(mc[list(p)] - tc).T))) for p in itertools.permutations(range(4)))
    return {"d_pct": 100 * (d / truth["d_um"] - 1), "d_px": (d - truth["d_um"]) / px,
            "depth_pct": 100 * (float(t["depth_nm"][k]) / truth["depth_nm"] - 1),
            "area_pct": 100 * (float(t["area_um2"][k]) / truth["area_um2"] - 1),
            "corner_px": corner / px}


def within(e, truth):
    """Goal flags (d, depth, area, corners); NaN fails."""
    d_tol = max(D_GOAL_PCT, 100 * D_GOAL_PX * truth["pixel_um"] / truth["d_um"])
    return (abs(e["d_pct"]) <= d_tol, abs(e["depth_pct"]) <= DEPTH_GOAL_PCT,
            abs(e["area_pct"]) <= AREA_GOAL_PCT, e["corner_px"] <= CORNER_GOAL_PX)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1-20", help='e.g. "1-20" or "1,5,9"')
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--ablate", choices=FAMILIES + ("all",), default=None,
                    help="switch one artefact family off ('all': every family off, the tip stays)")
    ap.add_argument("--format", choices=("gsf", "ibw"), default="gsf",
                    help="gsf: the trace only; ibw: HeightTrace and HeightRetrace (the z loop's lag taken out)")
    a = ap.parse_args(argv)
    seeds = parse_seeds(a.seeds)
    switches = {f: False for f in (FAMILIES if a.ablate == "all" else [a.ablate] if a.ablate else [])}
    print(f"indent_afm_feedback, seeds {a.seeds}, {a.size} x {a.size}, ablated: {a.ablate or 'none'}, {a.format}")
    print(f"goals: d {D_GOAL_PCT} % or {D_GOAL_PX:g} px (larger), depth {DEPTH_GOAL_PCT:g} %, "
          f"area {AREA_GOAL_PCT:g} %, corners {CORNER_GOAL_PX} px")
    print("seed pix_nm   d_um fill recov  d_err%   d_px  depth%   area%  corner_px border%  n  render_s  run_s  fails")
    rows, ok, failed, border, lag_err, missed = [], [], 0, [], [], []
    with tempfile.TemporaryDirectory(prefix="bench_feedback_") as tmp:
        for s in seeds:
            t0 = time.perf_counter()
            r = render_feedback(s, a.size, **switches)
            t_render = time.perf_counter() - t0
            tr = r.truth
            gsf, _ = write_feedback(r, tmp, f"fb_seed{s:03d}", a.format)
            head = (f"{s:4d} {tr['pixel_nm']:6.1f} {tr['d_um']:6.2f} {tr['fill']:4.2f} "
                    f"{tr['recovery_frac']:5.3f}")
            t1 = time.perf_counter()
            try:
                res = run_indents([gsf], None, IndentsOptions())
            except MarkcalError as exc:
                failed += 1
                ok.append((False,) * 4)
                print(f"{head}  FAILED after {time.perf_counter() - t1:.2f} s: {exc}", flush=True)
                continue
            t_run = time.perf_counter() - t1
            t = res.indents
            k = int(np.argmin(np.hypot(np.asarray(t["x_um"]) - tr["centre_um"][0],
                                       np.asarray(t["y_um"]) - tr["centre_um"][1])))
            e = errors(t, k, tr)
            border.append(100 * (float(t["depth_nm"][k]) / border_plane_depth_nm(r.height_nm) - 1))
            if res.summary.get("scan_lag_px") is not None and tr["feedback"]["enabled"]:
                lag_err.append(res.summary["scan_lag_px"] - tr["feedback"]["lag_px"])
            if "floor_missed" in res.files[0].info and tr["feedback"]["enabled"]:
                missed.append((res.files[0].info["floor_missed"], tr["feedback"]["descent_factor"], e["depth_pct"]))
            flags = within(e, tr)
            rows.append(e)
            ok.append(flags)
            fails = ",".join(n for n, f in zip(GOALS, flags) if not f)
            print(f"{head} {e['d_pct']:+7.2f} {e['d_px']:+6.2f} {e['depth_pct']:+7.2f} {e['area_pct']:+7.2f} "
                  f"{e['corner_px']:10.2f} {border[-1]:+7.2f} {len(t['x_um']):2d} {t_render:9.2f} {t_run:6.2f}  {fails}", flush=True)
    if not ok:
        return
    frac = 100 * np.mean(np.array(ok, float), axis=0)
    allf = 100 * np.mean(np.all(ok, axis=1))
    tag = f"ablate {a.ablate}" if a.ablate else "all"
    if rows:
        mx = {key: np.nanmax([abs(e[key]) for e in rows]) for key in rows[0]}
        errs = (f"max |d| {mx['d_pct']:.2f} % ({mx['d_px']:.2f} px), |depth| {mx['depth_pct']:.2f} %, "
                f"|area| {mx['area_pct']:.2f} %, corners {mx['corner_px']:.2f} px")
    else:
        errs = "no measurement"
    print(f"{tag} {len(ok)} seeds ({failed} failed): {errs}; within goal: d {frac[0]:.0f} %, depth "
          f"{frac[1]:.0f} %, area {frac[2]:.0f} %, corners {frac[3]:.0f} %; all four {allf:.0f} %")
    if border:
        b = np.abs(border)
        print(f"depth against a border-plane reading: within 10 % on {100 * np.mean(b <= 10):.0f} % of seeds, "
              f"max {b.max():.2f} %, median {np.median(border):+.2f} %")
    if lag_err:
        e = np.abs(lag_err)
        print(f"z loop lag against the renderer's ramp lag ({len(e)} maps): within 0.3 px on "
              f"{100 * np.mean(e <= 0.3):.0f} %, median |error| {np.median(e):.2f} px, max {e.max():.2f} px")
    if missed:
        m = np.array(missed, float)
        flag, short = m[:, 0] > 0, m[:, 2] < -5
        print(f"floor not reached (flag, {len(m)} maps with both directions): {flag.sum():.0f} flagged; depth over 5 % "
              f"short {short.sum():.0f}, of them flagged {(flag & short).sum():.0f}; flagged with the loop falling as "
              f"fast as the facets (descent >= 1) {(flag & (m[:, 1] >= 1)).sum():.0f} of {(m[:, 1] >= 1).sum():.0f}; "
              f"median depth error flagged {np.median(m[flag, 2]) if flag.any() else np.nan:+.2f} %, not flagged "
              f"{np.median(m[~flag, 2]) if (~flag).any() else np.nan:+.2f} %")


if __name__ == "__main__":
    sys.exit(main())
