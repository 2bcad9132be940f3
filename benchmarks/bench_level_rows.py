"""How far each scan line crossing the imprint lies off the surface after levelling (feedback renderer).

Usage: python benchmarks/bench_level_rows.py [--seeds 1-30]

Each seed of fixtures/indent_afm_feedback is drawn twice: as usual, and without the scanner's artefacts (no tilt,
bow, drift, line offsets, scars or noise), which is the truth the levelling should reach. The first is levelled
by ``level_single``; on the truth's far field (within 3 nm of its zero: imprint and pile-up left out), a plane is
taken off the difference (the level's own zero and tilt are not the question) and each line's median is its
error. Printed: the RMS of those errors over the lines that cross the imprint (under 40 % far field), per seed,
and their median and mean. Run with PYTHONPATH pointing at another checkout to compare codes.
"""
from __future__ import annotations

import argparse
import sys
import warnings

import numpy as np

from markcal.fixtures.indent_afm_feedback import render_feedback
from markcal.stages.indent_level import level_single

from bench_independent import parse_seeds  # noqa: E402  (benchmarks/ is the script's folder)


def line_errors_nm(seed: int, size_px: int = 256) -> float:
    """RMS (nm) of the levelled lines' errors over the lines crossing the imprint."""
    drawn = render_feedback(seed, size_px)
    truth = render_feedback(seed, size_px, scanner=False).height_nm.astype(float)
    far = np.abs(truth) < 3.0
    z = level_single(drawn.height_nm.astype(float), drawn.pixel_um).z_nm
    e = np.where(far, z - truth, np.nan)
    rr, cc = np.mgrid[0:size_px, 0:size_px]
    ok = np.isfinite(e)
    a = np.column_stack([cc[ok], rr[ok], np.ones(int(ok.sum()))]).astype(float)
    k = np.linalg.lstsq(a, e[ok], rcond=None)[0]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)          # lines without far field
        rows = np.nanmedian(e - (k[0] * cc + k[1] * rr + k[2]), axis=1)
    v = rows[(far.mean(axis=1) < 0.4) & np.isfinite(rows)]
    return float(np.sqrt(np.mean(v ** 2))) if v.size else float("nan")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1-30")
    a = ap.parse_args(argv)
    print(f"indent_afm_feedback seeds {a.seeds}: lines crossing the imprint, error after level_single (nm RMS)")
    errs = []
    for s in parse_seeds(a.seeds):
        errs.append(line_errors_nm(s))
        print(f"{s:4d} {errs[-1]:7.2f}", flush=True)
    print(f"{len(errs)} seeds: median {np.nanmedian(errs):.2f} nm, mean {np.nanmean(errs):.2f} nm")


if __name__ == "__main__":
    sys.exit(main())
