"""Single-imprint micrographs through the indents flow: imprints found, diagonal errors and time per image.

Images come from the renderer written without knowledge of markcal (``fixtures/indent_micrograph_independent``:
OM bright field, SEM with secondary or back-scattered electrons, grain, scratches, an information bar, edges
bowed by ``--bows``), and the real SEM image of ``../shared/realdata/sem_vickers/`` when it is there (its
careful manual reading: 19.09 µm, see ``tests/test_indent_micrograph.py``). Each image goes through the flow as
``markcal indents IMAGE`` takes it (outline detection, then dots, then squares with four clear edges), in
memory and on one BLAS thread, wall time per image. The issue's goals: the SEM mean diagonal within 2 % and a
1.7 Mpx SEM image within 2 s.

Usage: python benchmarks/bench_micrographs.py [--kinds sem,om] [--seeds 1-30] [--bows none,0.03,-0.03]
       [--only-mode bse] [--runs 1] [--real]
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np

from markcal.fixtures.indent_micrograph_independent import render_micrograph_independent
from markcal.pipeline.flows import indents as flow
from markcal.stages.errors import MarkcalError
from markcal.stages.image_io import Image, read_image

from bench_independent import parse_seeds  # noqa: E402  (benchmarks/ is the script's folder)

REAL_SEM = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "shared", "realdata", "sem_vickers",
                        "Indent_20230912_7kV_spot4.5_FOV100um_multiBSE_A_05.tif")


def run_flow(img: Image):
    """(table or None, error text, wall seconds) of one image through the flow."""
    t0 = time.perf_counter()
    try:
        with flow._one_blas_thread():
            res = flow._measure(img, None, flow.IndentsOptions(), lambda m: None, t0)
        return res.table, "", time.perf_counter() - t0
    except MarkcalError as exc:
        return None, str(exc), time.perf_counter() - t0


def match(table, truth_imprints, px):
    """Per true imprint: the relative d error (%) of the nearest found one within 2 µm, or None (missed)."""
    out = []
    for t in truth_imprints:
        if table is None or not len(table["x_um"]):
            out.append(None)
            continue
        dist = np.hypot(table["x_um"] - t["x_um"], table["y_um"] - t["y_um"])
        k = int(np.argmin(dist))
        out.append(100 * (table["d_um"][k] / t["d_um"] - 1) if dist[k] <= max(2.0, 5 * px) else None)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kinds", default="sem", help="om, sem or both")
    ap.add_argument("--seeds", default="1-30")
    ap.add_argument("--bows", default="none", help='edge bows (fraction of d/2, + inward), e.g. "none,0.03,-0.03"')
    ap.add_argument("--only-mode", default="", help='SEM only: "bse" or "se" (the renderer picks per seed)')
    ap.add_argument("--runs", type=int, default=1, help="runs per image; the median time is printed")
    ap.add_argument("--real", action="store_true", help="also the real SEM image (skipped when absent)")
    a = ap.parse_args(argv)
    bows = [None if b == "none" else float(b) for b in a.bows.split(",")]
    rows = []
    for kind in a.kinds.split(","):
        for seed in parse_seeds(a.seeds):
            for bow in bows:
                data, px, truth = render_micrograph_independent(seed, kind, bow)
                mode = truth["meta"].get("mode", "om")
                if a.only_mode and mode != a.only_mode:
                    continue
                img = Image(data=np.asarray(data, np.float64), pixel_um=px, kind="om",
                            source=f"{kind}{seed}", meta={})
                times = []
                for _ in range(max(1, a.runs)):
                    table, err, dt = run_flow(img)
                    times.append(dt)
                errs = match(table, truth["imprints"], px)
                n_found = 0 if table is None else len(table["x_um"])
                found = [e for e in errs if e is not None]
                rows.append((kind, mode, seed, bow, len(errs), len(found), n_found, errs, float(np.median(times))))
                txt = ", ".join("missed" if e is None else f"{e:+.2f} %" for e in errs)
                print(f"{kind:3s} {mode:3s} seed {seed:3d} bow {'none' if bow is None else f'{bow:+.2f}':>5s} "
                      f"{data.shape[0]}x{data.shape[1]}: {len(found)}/{len(errs)} found ({n_found} reported): {txt}"
                      f"{'  [' + err + ']' if err else ''}  {np.median(times):.2f} s", flush=True)
    if rows:
        print("\nsummary (median wall per image; d error of the imprints found):")
        for mode in sorted({r[1] for r in rows}):
            sub = [r for r in rows if r[1] == mode]
            e = np.array([x for r in sub for x in r[7] if x is not None])
            t = np.array([r[8] for r in sub])
            print(f"  {mode}: {len(sub)} images, {int(sum(r[5] for r in sub))}/{int(sum(r[4] for r in sub))} imprints "
                  f"found, {int(sum(r[6] - r[5] for r in sub))} extra; d error "
                  + (f"{e.min():+.2f} .. {e.max():+.2f} %, |d| ≤ 2 %: {np.mean(np.abs(e) <= 2) * 100:.0f} %; "
                     if len(e) else "none; ")
                  + f"time median {np.median(t):.2f} s, max {t.max():.2f} s, over 2 s: {int(np.sum(t > 2))}")
    if a.real:
        if not os.path.exists(REAL_SEM):
            print("\nreal SEM image: skipped (../shared/realdata/ absent)")
        else:
            img = read_image(REAL_SEM, None, None)
            times, table = [], None
            for _ in range(max(1, a.runs)):
                table, err, dt = run_flow(img)
                times.append(dt)
            d = "none" if table is None else ", ".join(f"{v:.3f}" for v in table["d_um"])
            print(f"\nreal SEM image {img.shape[0]}x{img.shape[1]} at {img.pixel_um:.4f} µm: d = {d} µm "
                  f"(careful manual reading 19.09 µm); wall median {np.median(times):.2f} s over {len(times)} runs")


if __name__ == "__main__":
    main()
