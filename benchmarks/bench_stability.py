"""How far one imprint's figures move when the same map is drawn again with a whisper of extra noise.

Usage: python benchmarks/bench_stability.py [--seeds 1-60] [--draws 4] [--noise-nm 0.05] [--format ibw]
                                           [--renderer feedback|ruled]

Each feedback-renderer seed (fixtures/indent_afm_feedback; ``--renderer ruled``: fixtures/indent_single_ruled,
every third seed with a corner 3 px from the border, the map's one channel) is measured as rendered and again with ``--draws``
independent draws of white noise of ``--noise-nm`` added to both scan directions: 5-25 % of the maps' own
noise (0.2-1.0 nm), far less than a second scan of the same imprint would differ by. A measurement that
meets its goals on one draw and misses them on the next has a cliff in it (a gate, a threshold on a pixel
count) that real maps will find. Printed per seed: the errors against the truth as rendered, and each
figure's spread (max - min over the draws and the map as rendered); at the end, the median spreads and the
number of seeds whose spread exceeds half of each goal (d 0.25 %, area 0.5 %, corners 0.75 px, depth 0.5 %).
"""
from __future__ import annotations

import argparse
import sys
import tempfile

import numpy as np

from markcal.fixtures.indent_afm_feedback import render_feedback, write_feedback
from markcal.fixtures.indent_maps import with_more_noise
from markcal.fixtures.indent_single_ruled import render_single_ruled, write_single_ruled
from markcal.pipeline.flows.indents import IndentsOptions, run_indents
from markcal.stages.errors import MarkcalError

from bench_feedback import errors  # noqa: E402  (benchmarks/ is the script's folder)
from bench_independent import afm_errors, nearest_row, parse_seeds  # noqa: E402

KEYS = ("d_pct", "area_pct", "corner_px", "depth_pct")
HALF_GOALS = (0.25, 0.5, 0.75, 0.5)


RULED_KEYS = ("d_err_pct", "area_err_pct", "corner_max_px", "depth_err_pct")


def measure(render, folder, name, fmt):
    """Errors (``KEYS``) of the imprint nearest the true centre, NaN where the run fails."""
    ruled = not hasattr(render, "retrace_nm")
    path, _ = write_single_ruled(render, folder, name) if ruled else write_feedback(render, folder, name, fmt)
    try:
        t = run_indents([path], None, IndentsOptions()).indents
    except MarkcalError:
        return np.full(len(KEYS), np.nan)
    tr = render.truth
    if ruled:
        e = afm_errors(t, nearest_row(t, *tr["centre_um"]), tr)
        return np.array([e[key] for key in RULED_KEYS])
    k = nearest_row(t, *tr["centre_um"])
    e = errors(t, k, tr)
    return np.array([e[key] for key in KEYS])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1-60")
    ap.add_argument("--draws", type=int, default=4)
    ap.add_argument("--noise-nm", type=float, default=0.05)
    ap.add_argument("--format", choices=("gsf", "ibw"), default="ibw", help="feedback renderer's file format")
    ap.add_argument("--renderer", choices=("feedback", "ruled"), default="feedback")
    a = ap.parse_args(argv)
    print(f"indent_afm_{a.renderer} seeds {a.seeds}: as rendered and {a.draws} draws of {a.noise_nm:g} nm white noise "
          f"more{', ' + a.format if a.renderer == 'feedback' else ''}")
    print("seed  d_err%  area%  corner_px | spread: d%   area%  corner_px  depth%")
    spreads = []
    with tempfile.TemporaryDirectory(prefix="bench_stability_") as tmp:
        for s in parse_seeds(a.seeds):
            if a.renderer == "ruled":
                r = render_single_ruled(s, size_px=256, corner_margin_px=3.0 if s % 3 == 0 else None)
            else:
                r = render_feedback(s, 256)
            rows = [measure(r, tmp, f"s{s}", a.format)]
            for k in range(a.draws):
                rows.append(measure(with_more_noise(r, k, a.noise_nm), tmp, f"s{s}_{k}", a.format))
            o = np.array(rows)
            sp = np.nanmax(o, axis=0) - np.nanmin(o, axis=0) if np.isfinite(o).any() else np.full(len(KEYS), np.nan)
            spreads.append(sp)
            print(f"{s:4d} {o[0, 0]:+7.2f} {o[0, 1]:+6.2f} {o[0, 2]:10.2f} | {sp[0]:10.2f} {sp[1]:7.2f} {sp[2]:10.2f} "
                  f"{sp[3]:7.2f}", flush=True)
    sp = np.array(spreads)
    med = np.nanmedian(sp, axis=0)
    over = [int(np.sum(sp[:, j] > h)) for j, h in enumerate(HALF_GOALS)]
    print(f"{len(sp)} seeds: median spread d {med[0]:.2f} %, area {med[1]:.2f} %, corners {med[2]:.2f} px, depth "
          f"{med[3]:.2f} %; max d {np.nanmax(sp[:, 0]):.2f} %, area {np.nanmax(sp[:, 1]):.2f} %, corners "
          f"{np.nanmax(sp[:, 2]):.2f} px, depth {np.nanmax(sp[:, 3]):.2f} %; seeds spread over half a goal: d {over[0]}, "
          f"area {over[1]}, corners {over[2]}, depth {over[3]}")


if __name__ == "__main__":
    sys.exit(main())
