"""Systematic search over the open readings of paper 003 (issue 15), scored against Tables 1-2.

Every combination of the open choices of :mod:`markcal.stages.servo_reading`
(plant form, numerator, units of plant / PID / feed-forward, integral form,
S-curve jerk, settling band and origin, sine window) is simulated on the
paper's baseline ("without CCA") cases -- S-curve moves of 10/20/30 mm at
0.1 m/s and 10 m/s^2, 10 mm sines at 0.1-2 Hz -- and scored by the RMS of
ln(ours / paper) over Table 1 (overshoot, settling) and Table 2 (MAE, STD).

Run: .venv/bin/python benchmarks/servo_readings.py [--top N] [--markdown]
The metric-only choices (band, origin, sine window) reuse one simulation.
"""
from __future__ import annotations

import argparse
import itertools
import math
import time
from dataclasses import replace

from markcal.stages.servo_reading import (BANDS, DEFAULT_READING, PAPER_T1_BASE, PAPER_T2_BASE, Reading,
                                          baseline_rows, score_rows)

DYNAMIC = {   # choices that change the simulation
    "plant": ("a0", "no_a0"),
    "b0_scale": (1.0, 0.1),
    "plant_unit": ("mm", "um"),
    "ctrl_unit": ("mm", "um"),
    "ff_unit": ("mm", "um"),
    "integral": ("inv", "gain"),
}
JERKS = (math.inf, 1_000_000.0, 300_000.0)
METRIC = {"band": BANDS, "origin": ("end", "start")}
WINDOWS = (("last", 3.0), ("whole", 2.0), ("whole", 3.0), ("whole", 5.0))


def search():
    """Yield (reading, rows, score) for every combination."""
    keys = list(DYNAMIC)
    for combo in itertools.product(*DYNAMIC.values()):
        base = Reading(**dict(zip(keys, combo)))
        # the sine rows do not depend on jerk / band / origin: simulate them once per window
        sines = {w: baseline_rows(replace(base, sine_window=w[0], sine_periods=w[1]), strokes_mm=())["t2"]
                 for w in WINDOWS}
        for jerk in JERKS:
            steps = {}
            for band, origin in itertools.product(*METRIC.values()):
                rd = replace(base, jerk_mm_s3=jerk, band=band, origin=origin)
                steps[(band, origin)] = baseline_rows(rd, freqs_hz=())["t1"]
            for (band, origin), t1 in steps.items():
                for w in WINDOWS:
                    rd = replace(base, jerk_mm_s3=jerk, band=band, origin=origin, sine_window=w[0],
                                 sine_periods=w[1])
                    rows = {"t1": t1, "t2": sines[w]}
                    yield rd, rows, score_rows(rows)


def fmt_rows(rows):
    t1 = " ".join(f"{rows['t1'][s][0]:.0f}/{rows['t1'][s][1]:.1f}" for s in PAPER_T1_BASE)
    t2 = " ".join(f"{rows['t2'][f][0]:.1f}/{rows['t2'][f][1]:.1f}" for f in PAPER_T2_BASE)
    return t1, t2


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--top", type=int, default=15)
    ap.add_argument("--markdown", action="store_true", help="print the top rows as a README table")
    ap.add_argument("--b0-scale", type=float, default=None, help="only readings with this numerator scale")
    ap.add_argument("--plant", default=None, help="only readings with this plant form (a0, no_a0)")
    a = ap.parse_args()
    t0 = time.perf_counter()
    res = sorted((x for x in search() if (a.b0_scale is None or x[0].b0_scale == a.b0_scale)
                  and (a.plant is None or x[0].plant == a.plant)), key=lambda x: x[2]["score"])
    print(f"{len(res):,} readings scored in {time.perf_counter() - t0:.1f} s")
    print("paper T1 (overshoot µm / settling ms, 10/20/30 mm):",
          " ".join(f"{v[0]:.0f}/{v[1]:.1f}" for v in PAPER_T1_BASE.values()))
    print("paper T2 (MAE/STD µm, 0.1/0.2/0.5/1/2 Hz):", " ".join(f"{v[0]}/{v[1]}" for v in PAPER_T2_BASE.values()))
    seen = set()
    shown = 0
    for rd, rows, sc in res:
        t1, t2 = fmt_rows(rows)
        key = (t1, t2)
        if key in seen:            # readings that give identical numbers: show the first only
            continue
        seen.add(key)
        if a.markdown:
            print(f"| {sc['score']:.3f} | {sc['t1_within']}/{sc['t1_n']} | {sc['t2_within']}/{sc['t2_n']} | "
                  f"{rd.label} | {t1} | {t2} |")
        else:
            print(f"{sc['score']:.3f} T1 {sc['t1_within']}/{sc['t1_n']} T2 {sc['t2_within']}/{sc['t2_n']} | "
                  f"{rd.label}\n      T1 {t1} | T2 {t2}")
        shown += 1
        if shown >= a.top:
            break
    d = [x for x in res if x[0] == DEFAULT_READING]
    if d:
        print(f"default reading: score {d[0][2]['score']:.3f}, rank {res.index(d[0]) + 1} of {len(res)}")


if __name__ == "__main__":
    main()
