"""Indents flow: the issue's speed goals (256² single map, 512² and 1024² AFM arrays, 1 Mpx OM array,
the real 1.7 Mpx SEM image; wall and CPU seconds, load average) and accuracy on unseen renders.

Usage: python benchmarks/bench_indents.py [--runs 5] [--afm-seeds 10] [--om-seeds 4] [--micro-seeds 10]
       [--rounded-seeds 8] [--single-seeds 10] [--om-hard-seeds 10] [--om-speed-seeds 12] [--dense-seeds 2] [--lag-seeds 12]
       [--*-first-seed N]

Speed: read the float32 TIFF -> level -> detect -> measure -> index and register,
in memory (``measure_file``), median of ``--runs``. Accuracy: seeds 1000+ (never
used by the tests), 5 x 5 arrays of 1, 2 and 3 µm marks, errors against truth.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

import numpy as np

from markcal.fixtures.indent_maps import (AfmOptions, OmOptions, array_toml, ibw_bytes, render_afm, render_om,
                                         tiff_bytes)
from markcal.pipeline.flows.indents import IndentsOptions, measure_file, optics_reference, read_array_spec, run_indents


#: the retrace of the two-direction speed cases: the trace moved this far along the fast axis (px), its own noise
TWO_DIRECTIONS_OFFSET_PX = 3.0


def _two_directions_ibw(path, z_nm, pixel_um, noise_nm=0.5, seed=0):
    """``path``: an Asylum IBW holding ``z_nm`` as HeightTrace and as HeightRetrace, the retrace moved by
    ``TWO_DIRECTIONS_OFFSET_PX`` along the fast axis with noise of its own (a z loop's lag both ways), so the
    flow measures it too."""
    from scipy import ndimage
    z = np.asarray(z_nm, float)
    back = ndimage.shift(z, (0.0, -TWO_DIRECTIONS_OFFSET_PX), order=3, mode="nearest")
    back = back + np.random.default_rng(seed).normal(0.0, noise_nm, z.shape)
    with open(path, "wb") as fh:
        fh.write(ibw_bytes({"HeightTrace": z * 1e-9, "HeightRetrace": back * 1e-9}, pixel_um * 1e-6))
    return path


def _files(folder, r):
    t = r.truth
    path = os.path.join(folder, "map.tif")
    with open(path, "wb") as fh:
        fh.write(tiff_bytes(r.data, r.pixel_um, zunit="nm" if r.kind == "afm" else None))
    spec = os.path.join(folder, "array.toml")
    with open(spec, "w") as fh:
        fh.write(array_toml(t["rows"], t["cols"], t["pitch_um"], t["nominal_diameter_um"]))
    return path, read_array_spec(spec)


def _errors(table, truth):
    """Each measured imprint against the nearest true one: centre distance, diameter error, depth error, x error
    (µm, µm, nm, µm); and how many true imprints were missed and measured ones were false."""
    txy = np.array([[i["x_um"], i["y_um"]] for i in truth["imprints"]])
    rows = []
    used = set()
    for k in range(len(table["x_um"])):
        d = np.hypot(txy[:, 0] - table["x_um"][k], txy[:, 1] - table["y_um"][k])
        j = int(np.argmin(d))
        used.add(j)
        t = truth["imprints"][j]
        rows.append([d[j], table["diameter_um"][k] - t["diameter_um"],
                     table["depth_nm"][k] - t.get("depth_nm", np.nan), table["x_um"][k] - txy[j, 0]])
    return np.array(rows), len(truth["imprints"]) - len(used), len(table["x_um"]) - len(used)


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--afm-seeds", type=int, default=10)
    ap.add_argument("--om-seeds", type=int, default=4)
    ap.add_argument("--bulge", type=float, default=0.0, help="facet bulge of the AFM renders (model mismatch)")
    ap.add_argument("--om-nominal", type=float, default=None, help="OM: one nominal size (µm) for every seed")
    ap.add_argument("--om-first-seed", type=int, default=1000)
    ap.add_argument("--single-seeds", type=int, default=10, help="single real-like imprints (issue 20 goals)")
    ap.add_argument("--micro-seeds", type=int, default=10, help="single imprints in OM and SEM micrograph renders")
    ap.add_argument("--micro-first-seed", type=int, default=3000, help="first micrograph seed")
    ap.add_argument("--rounded-seeds", type=int, default=8, help="arrays with Gaussian tip rounding (depth)")
    ap.add_argument("--rounded-first-seed", type=int, default=4000, help="first Gaussian-rounded seed")
    ap.add_argument("--single-first-seed", type=int, default=2000, help="first single-imprint seed")
    ap.add_argument("--om-hard-seeds", type=int, default=0,
                    help="OM arrays from the micrograph renderer (one-sided shading, lines, halo, vignetting)")
    ap.add_argument("--om-hard-first-seed", type=int, default=5000, help="first hard OM array seed")
    ap.add_argument("--om-hard-na", type=float, default=None,
                    help="hard OM arrays: Airy optics of this NA at 550 nm (default: Gaussian blur of 1 px)")
    ap.add_argument("--om-hard-sizes", default="1,2,3", help="hard OM arrays: nominal sizes (µm), cycled over the seeds")
    ap.add_argument("--om-hard-objective-na", type=float, default=None,
                    help="hard OM arrays: measure with the objective's NA given (PSF held, not fitted)")
    ap.add_argument("--om-hard-reference-um", type=float, default=None,
                    help="hard OM arrays: measure with --optics-from a reference array of this size (seed + 100, "
                         "same optics)")
    ap.add_argument("--lag-seeds", type=int, default=0,
                    help="5 x 5 AFM arrays scanned both ways through a PI z loop (fixtures z_loop_scans), with the "
                         "spec, against the same maps without the loop")
    ap.add_argument("--dense-seeds", type=int, default=0,
                    help="dense AFM arrays (5 x 5 to 12 x 12, imprints 1.5-4 diameters apart) on seeds 1..N")
    ap.add_argument("--om-speed-seeds", type=int, default=0,
                    help="time the 1 Mpx hard OM case of 1 µm imprints (Airy NA 0.9) on this many seeds from 5700")
    a = ap.parse_args(argv)
    tmp = tempfile.mkdtemp(prefix="bench_indents_")
    print("machine: 2 cores shared with other jobs; timings are noisy", file=sys.stderr)

    if a.runs:
        _speed(a, tmp)

    if a.om_speed_seeds:
        _om_speed_seeds(a, tmp)
    if a.micro_seeds:
        _micrograph_sweep(a)
        _real_sem(a)
    if a.rounded_seeds:
        _rounded_sweep(a)
    if a.single_seeds:
        _single_sweep(a, tmp)
    if a.afm_seeds:
        _afm_sweep(a, tmp)
    if a.om_seeds:
        _om_sweep(a, tmp)
    if a.dense_seeds:
        _dense_sweep(a, tmp)
    if a.lag_seeds:
        _lag_sweep(a, tmp)
    if a.om_hard_seeds:
        _om_hard_sweep(a, tmp)


def _time_file(path, spec, runs, opts=None):
    """Wall and CPU seconds of ``measure_file`` (lists over ``runs``) and the last result."""
    times, cpu = [], []
    for _ in range(runs):
        t0, c0 = time.perf_counter(), time.process_time()
        f = measure_file(path, spec, opts or IndentsOptions())
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return times, cpu, f


def _speed(a, tmp):
    """The issue's speed goals: file in memory -> table (``measure_file``), median of ``--runs``."""
    from markcal.fixtures.indent_single import SingleOptions, render_single, single_ibw
    print(f"speed, median of {a.runs} runs of measure_file (read, level, detect, measure); load average "
          f"{' '.join(f'{v:.1f}' for v in os.getloadavg())} at start")
    print("case                                      n   wall_s  (min)    cpu_s  goal_s")
    cases = []
    r = render_single(2000, SingleOptions())
    path = os.path.join(tmp, "single.ibw")
    with open(path, "wb") as fh:
        fh.write(single_ibw(r))
    cases.append(("256x256 single-imprint AFM map (IBW)", path, None, 0.3))
    cases.append(("  the same, trace and retrace (both measured)",
                  _two_directions_ibw(os.path.join(tmp, "single2.ibw"), r.data, r.pixel_um), None, 0.3))
    from markcal.fixtures.indent_afm_feedback import render_feedback, write_feedback
    path, _ = write_feedback(render_feedback(7, 1024), tmp, "feedback1024", "ibw")
    cases.append(("1024x1024 single imprint, trace and retrace (feedback seed 7; trace only measured)", path, None,
                  2.0))
    for size, goal in ((512, 0.5), (1024, 2.0)):
        r = render_afm(1000, AfmOptions(size_px=size))
        sub = os.path.join(tmp, f"afm{size}")
        os.makedirs(sub, exist_ok=True)
        path, spec = _files(sub, r)
        cases.append((f"{size}x{size} AFM map, 5x5 array", path, spec, goal))
        two = _two_directions_ibw(os.path.join(sub, "map2.ibw"), r.data, r.pixel_um)
        cases.append(("  the same, trace and retrace", two, spec, goal))
        cases.append(("  the same without the spec (25: retrace not measured)", two, None, goal))
    r = render_om(1000, OmOptions(size_px=1024, pixel_um=0.05, nominal_um=2.0))
    sub = os.path.join(tmp, "om1024")
    os.makedirs(sub, exist_ok=True)
    path, spec = _files(sub, r)
    cases.append(("1024x1024 OM micrograph, 5x5 array", path, spec, 2.0))
    # hard OM arrays (micrograph renderer: one-sided shading, edge and ridge lines, halo, vignetting), Airy
    # NA 0.9, 1000 x 1000 at 0.1 µm, 5 x 5 at an 18 µm pitch; 1 µm imprints are the slow case (crease profile)
    for seed, d_um, na in ((5702, 1.0, None), (5702, 1.0, 0.9), (5703, 2.0, None), (5704, 3.0, None)):
        path, spec = _hard_om_file(tmp, seed, d_um)
        name = f"1000x1000 hard OM, {d_um:.0f} um" + (" --objective-na 0.9" if na else "")
        cases.append((name, path, spec, 2.0, IndentsOptions(kind="om", objective_na=na)))
    for name, path, spec, goal, *opts in cases:
        times, cpu, f = _time_file(path, spec, a.runs, *opts)
        print(f"{name:41s} {len(f.imprints):2d} {np.median(times):7.3f} ({min(times):6.3f}) {np.median(cpu):7.3f}  "
              f"{goal:5.1f}", flush=True)
    print(f"load average {' '.join(f'{v:.1f}' for v in os.getloadavg())} at end")


def _hard_om_file(tmp, seed, d_um):
    """A 1000 x 1000 hard OM array at 0.1 µm (5 x 5 at an 18 µm pitch, Airy NA 0.9) and its spec."""
    from markcal.fixtures.indent_micrograph import MicrographOptions, render_micrograph
    r = render_micrograph(seed, MicrographOptions(rows=1000, cols=1000, grid=(5, 5, 18.0), d_um=d_um, na=0.9))
    path = os.path.join(tmp, f"om_hard_{seed}_{d_um:g}.tif")
    with open(path, "wb") as fh:
        fh.write(tiff_bytes(r.data, r.pixel_um))
    spec = os.path.join(tmp, f"om_hard_{seed}_{d_um:g}.toml")
    with open(spec, "w") as fh:
        fh.write(array_toml(5, 5, 18.0, d_um))
    return path, read_array_spec(spec)


def _om_speed_seeds(a, tmp):
    """The time of the slow OM case varies with the image (the solvers' steps): one seed is not enough."""
    print(f"\n1 Mpx hard OM, 25 imprints of 1 µm, Airy NA 0.9, seeds 5700..{5699 + a.om_speed_seeds}: median of "
          f"{max(a.runs, 3)} measure_file runs each (goal 2 s); load {' '.join(f'{v:.1f}' for v in os.getloadavg())}")
    med = []
    for seed in range(5700, 5700 + a.om_speed_seeds):
        path, spec = _hard_om_file(tmp, seed, 1.0)
        measure_file(path, spec, IndentsOptions(kind="om"))              # warm: numba and FFT plans
        times, _cpu, _f = _time_file(path, spec, max(a.runs, 3), IndentsOptions(kind="om"))
        med.append(float(np.median(times)))
        print(f"seed {seed}: {med[-1]:.3f} s", flush=True)
    print(f"median {np.median(med):.3f} s, max {max(med):.3f} s, {sum(m > 2.0 for m in med)} of {len(med)} over 2 s")


def _micrograph_sweep(a):
    """Single imprints in micrograph renders (fixtures/indent_micrograph, seeds 3000+), OM and SEM."""
    from markcal.fixtures.indent_micrograph import MicrographOptions, render_micrograph
    from markcal.stages.indent_micrograph import measure_micrograph
    s0 = a.micro_first_seed
    print(f"\nmicrographs, seeds {s0}..{s0 + a.micro_seeds - 1}, 360 x 480 at 0.1 µm (SEM with a 40-row bar); "
          "goals: d within 1 % or 1 px, corners 1.5 px")
    print("style seed  d_px    d_err_%  d_err_px  corner_max_px  n  wall_s")
    for style in ("om", "sem"):
        v = []
        for i in range(a.micro_seeds):
            seed = s0 + i
            r = render_micrograph(seed, MicrographOptions(style=style, bar_rows=40 if style == "sem" else 0))
            t = r.truth["imprints"][0]
            px = r.pixel_um
            t0 = time.perf_counter()
            imps, _bar = measure_micrograph(r.data, px)
            wall = time.perf_counter() - t0
            if not imps:
                print(f"{style:5s} {seed}  none found")
                v.append((np.nan, np.nan, np.nan, wall))
                continue
            m = min(imps, key=lambda q: np.hypot(q.x_um - t["x_um"], q.y_um - t["y_um"]))
            tc = np.array(t["corners_um"]) / px
            cmax = max(np.min(np.hypot(*(m.corners_um / px - c).T)) for c in tc)
            row = (100 * (m.d_um / t["d_um"] - 1), (m.d_um - t["d_um"]) / px, cmax, wall)
            v.append(row)
            print(f"{style:5s} {seed} {t['d_um'] / px:5.0f}  {row[0]:+7.2f}  {row[1]:+8.2f}  {cmax:13.2f}  "
                  f"{len(imps)}  {wall:6.2f}", flush=True)
        v = np.array(v)
        ok = np.mean((np.abs(v[:, 0]) <= 1.0) | (np.abs(v[:, 1]) <= 1.0))
        print(f"{style} all: d error mean {np.nanmean(v[:, 1]):+.2f} px, max |{np.nanmax(np.abs(v[:, 1])):.2f}| px "
              f"({np.nanmax(np.abs(v[:, 0])):.2f} %), within goal {100 * ok:.0f} %; corners max "
              f"{np.nanmax(v[:, 2]):.2f} px, within 1.5 px {100 * np.mean(v[:, 2] <= 1.5):.0f} %; "
              f"wall median {np.median(v[:, 3]):.2f} s")


def _real_sem(a):
    """The real FEI SEM image (1536 x 1103, one ~19 µm imprint): time of measure_file, median of runs."""
    from pathlib import Path
    env = os.environ.get("MARKCAL_REALDATA")
    root = Path(env) if env else Path(__file__).resolve().parents[1] / ".." / "shared" / "realdata"
    if not root.is_dir():
        root = Path("/work/shared/realdata")
    path = root / "sem_vickers" / "Indent_20230912_7kV_spot4.5_FOV100um_multiBSE_A_05.tif"
    if not path.is_file():
        print("real SEM image not present: skipped")
        return
    times, cpu, f = _time_file(str(path), None, max(1, a.runs))
    t = f.table
    print(f"real SEM image (1.7 Mpx): {len(t['id'])} imprint(s), d1 {t['diag1_um'][0]:.3f} µm, d2 "
          f"{t['diag2_um'][0]:.3f} µm, d {t['d_um'][0]:.3f} µm, bar {f.info.get('bar_rows')} rows; wall median "
          f"{np.median(times):.2f} s (min {min(times):.2f}), CPU median {np.median(cpu):.2f} s, goal <= 2 s; "
          f"load average {os.getloadavg()[0]:.1f}")


def _rounded_sweep(a):
    """Arrays with Gaussian tip rounding (fixtures/indent_rounded, seeds 4000+): depth against the true floor."""
    from markcal.fixtures.indent_rounded import RoundedOptions, render_rounded_afm
    from markcal.stages.image_io import Image
    from markcal.stages.indent_array import ArraySpec
    from markcal.pipeline.flows.indents import _measure
    s0 = a.rounded_first_seed
    print(f"\nGaussian-rounded arrays, seeds {s0}..{s0 + a.rounded_seeds - 1}, 3 x 3 of 2 µm, 256 x 256 over 16 µm; "
          "goal: depth bias <= 1 nm, RMS <= 2 nm against the rounded surface's floor")
    print("seed rounding_um  depth_bias_nm  depth_rms_nm  apex_bias_nm  apex_rms_nm")
    allv = []
    for i in range(a.rounded_seeds):
        seed = s0 + i
        r = render_rounded_afm(seed, RoundedOptions())
        img = Image(data=r.data.astype(float), pixel_um=r.pixel_um, kind="afm", source=f"rounded{seed}")
        res = _measure(img, ArraySpec(3, 3, 5.0, 2.0), IndentsOptions(), lambda m: None, time.perf_counter())
        e = []
        for t in r.truth["imprints"]:
            k = int(np.argmin(np.hypot(res.table["x_um"] - t["x_um"], res.table["y_um"] - t["y_um"])))
            e.append((res.table["depth_nm"][k] - t["floor_depth_nm"], res.table["apex_depth_nm"][k] - t["floor_depth_nm"]))
        e = np.array(e)
        allv.append(e)
        print(f"{seed} {r.truth['rounding_um']:11.3f} {np.mean(e[:, 0]):+14.2f} {np.sqrt(np.mean(e[:, 0] ** 2)):13.2f} "
              f"{np.nanmean(e[:, 1]):+13.2f} {np.sqrt(np.nanmean(e[:, 1] ** 2)):12.2f}", flush=True)
    e = np.vstack(allv)
    print(f"all {len(e)}: depth_nm bias {np.mean(e[:, 0]):+.2f} nm, RMS {np.sqrt(np.mean(e[:, 0] ** 2)):.2f} nm; "
          f"apex_depth_nm (facet model) bias {np.nanmean(e[:, 1]):+.2f} nm, RMS "
          f"{np.sqrt(np.nanmean(e[:, 1] ** 2)):.2f} nm")


def _single_sweep(a, tmp):
    """Single imprints (fixtures/indent_single, seeds 2000+; odd seeds: a corner 3 px from the border)."""
    from markcal.fixtures.indent_single import SingleOptions, render_single, single_ibw
    s0 = a.single_first_seed
    print(f"\nsingle imprints, seeds {s0}..{s0 + a.single_seeds - 1}, 256 x 256, multi-channel IBW; goals: "
          "d 0.5 % or 1 px, depth 1 %, area 1 %, corners 1.5 px, <= 0.3 s")
    print("seed fill margin_px  d_err_%  d_err_px  depth_err_%  area_err_%  corner_max_px  cut  wall_s")
    rows = []
    for i in range(a.single_seeds):
        seed = s0 + i
        r = render_single(seed, SingleOptions(corner_margin_px=3.0 if i % 2 else None))
        t = r.truth["imprints"][0]
        path = os.path.join(tmp, "single.ibw")
        with open(path, "wb") as fh:
            fh.write(single_ibw(r))
        t0 = time.perf_counter()
        f = measure_file(path, None, IndentsOptions())
        wall = time.perf_counter() - t0
        k = int(np.argmax(f.table["d_um"]))
        m = f.imprints[k]
        tc = np.array(t["corners_um"])
        cmax = max(np.min(np.hypot(*(tc - c).T)) for c in m.corners_um) / r.pixel_um
        row = (100 * (m.d_um / t["d_um"] - 1), (m.d_um - t["d_um"]) / r.pixel_um,
               100 * (m.depth_nm / t["depth_nm"] - 1), 100 * (m.area_um2 / t["area_um2"] - 1), cmax, wall)
        rows.append(row)
        print(f"{seed} {r.truth['fill']:.2f} {'3' if i % 2 else '-':>6}  {row[0]:+7.2f}  {row[1]:+8.2f}  "
              f"{row[2]:+10.2f}  {row[3]:+10.2f}  {row[4]:13.2f}  {int(m.cut_by_border):3d}  {wall:6.2f}", flush=True)
    v = np.array(rows)
    d_ok = np.mean((np.abs(v[:, 0]) <= 0.5) | (np.abs(v[:, 1]) <= 1.0))
    print(f"all: |d| max {np.nanmax(np.abs(v[:, 0])):.2f} % ({np.nanmax(np.abs(v[:, 1])):.2f} px), within goal "
          f"{100 * d_ok:.0f} %; |depth| max {np.nanmax(np.abs(v[:, 2])):.2f} %; |area| max "
          f"{np.nanmax(np.abs(v[:, 3])):.2f} %; corners max {np.nanmax(v[:, 4]):.2f} px; wall median "
          f"{np.median(v[:, 5]):.2f} s")


def _afm_sweep(a, tmp):
    print(f"\nAFM accuracy, seeds 1000..{999 + a.afm_seeds}, 512 x 512 over 50 µm, facet bulge {a.bulge}")
    print("seed nominal tilt_deg  n  missed false  centre_rms_nm  diam_rms_nm  diam_max_nm  depth_rms_nm")
    allv = []
    for i in range(a.afm_seeds):
        seed = 1000 + i
        r = render_afm(seed, AfmOptions(nominal_um=[1.0, 2.0, 3.0][i % 3], facet_bulge=a.bulge))
        path, spec = _files(tmp, r)
        res = run_indents([path], spec)
        e, missed, false = _errors(res.indents, r.truth)
        allv.append(e)
        print(f"{seed} {r.truth['nominal_diameter_um']:5.1f} {r.truth['tilt_deg']:8.2f} {len(e):3d} {missed:4d} "
              f"{false:5d} {1000 * np.sqrt(np.mean(e[:, 0] ** 2)):12.1f} {1000 * np.sqrt(np.mean(e[:, 1] ** 2)):12.1f} "
              f"{1000 * np.abs(e[:, 1]).max():12.1f} {np.sqrt(np.mean(e[:, 2] ** 2)):12.2f}")
    e = np.vstack(allv)
    print(f"all {len(e)}: centre RMS {1000 * np.sqrt(np.mean(e[:, 0] ** 2)):.1f} nm (goal 15), diameter RMS "
          f"{1000 * np.sqrt(np.mean(e[:, 1] ** 2)):.1f} nm (goal 20), "
          f"depth RMS {np.sqrt(np.mean(e[:, 2] ** 2)):.2f} nm "
          "(goal 2)")



#: dense arrays: (rows = cols, pitch µm, nominal diameter µm), the field 6 µm wider than the array, 512 x 512
DENSE_ARRAYS = ((5, 8.0, 3.0), (7, 6.0, 3.0), (8, 5.0, 3.0), (10, 4.5, 3.0), (12, 3.5, 2.0))


def _dense_sweep(a, tmp):
    """AFM arrays whose imprints stand 1.5-4 diameters apart (session 27: until then those masking over 30 % of the
    field were levelled as one imprint)."""
    print(f"\ndense AFM arrays, seeds 1..{a.dense_seeds}, 512 x 512; goals: centre RMS 15 nm, diameter RMS 20 nm")
    print("rows pitch_um d_um seed  masked  n missed false  centre_rms_nm  diam_rms_nm  diam_max_nm  depth_rms_nm")
    from markcal.stages.level import level_afm
    for rows, pitch, nominal in DENSE_ARRAYS:
        for seed in range(1, a.dense_seeds + 1):
            r = render_afm(seed, AfmOptions(rows=rows, cols=rows, pitch_um=pitch, nominal_um=nominal,
                                            field_um=rows * pitch + 6.0, size_px=512))
            path, spec = _files(tmp, r)
            e, missed, false = _errors(run_indents([path], spec).indents, r.truth)
            masked = level_afm(r.data, r.pixel_um).mask.mean()
            print(f"{rows:4d} {pitch:7.1f} {nominal:4.1f} {seed:4d}  {masked:6.2f} {len(e):3d} {missed:6d} {false:5d} "
                  f"{1000 * np.sqrt(np.mean(e[:, 0] ** 2)):14.1f} {1000 * np.sqrt(np.mean(e[:, 1] ** 2)):12.1f} "
                  f"{1000 * np.abs(e[:, 1]).max():12.1f} {np.sqrt(np.mean(e[:, 2] ** 2)):13.2f}", flush=True)


def _lag_sweep(a, tmp):
    """AFM arrays scanned through a z loop, trace and retrace in one IBW, measured with the spec: on the trace, the
    positions moved back by the imprints' own shift (five of them measured on the retrace too; summary.json
    ``imprint_shift_px``). The same maps without the loop (the surface as rendered, trace only) in the same run:
    the loop should cost nothing."""
    from markcal.fixtures.indent_afm_feedback import z_loop_scans
    print(f"\nAFM arrays through a z loop (5 x 5, 512 x 512), seeds 1..{a.lag_seeds}, with the spec; goals: centre RMS "
          "15 nm, diameter RMS 20 nm")
    print("seed  ramp_lag_px | loop: lag_px  shift_px  centre_rms_nm  x_bias_nm  diam_rms_nm  diam_median_nm | "
          "no loop: centre_rms_nm  diam_rms_nm")
    rows = []
    for seed in range(1, a.lag_seeds + 1):
        r = render_afm(seed, AfmOptions())
        trace, retrace, loop = z_loop_scans(r.data, seed)
        _, spec = _files(tmp, r)
        path, flat = os.path.join(tmp, "loop.ibw"), os.path.join(tmp, "flat.ibw")
        with open(path, "wb") as fh:
            fh.write(ibw_bytes({"HeightTrace": trace * 1e-9, "HeightRetrace": retrace * 1e-9}, r.pixel_um * 1e-6))
        with open(flat, "wb") as fh:
            fh.write(ibw_bytes({"HeightTrace": r.data * 1e-9}, r.pixel_um * 1e-6))
        res = run_indents([path], spec)
        e, _missed, _false = _errors(res.indents, r.truth)
        f, _missed, _false = _errors(run_indents([flat], spec).indents, r.truth)
        row = [1000 * np.sqrt(np.mean(e[:, 0] ** 2)), 1000 * float(np.mean(e[:, 3])),
               1000 * np.sqrt(np.mean(e[:, 1] ** 2)), 1000 * float(np.median(e[:, 1])),
               1000 * np.sqrt(np.mean(f[:, 0] ** 2)), 1000 * np.sqrt(np.mean(f[:, 1] ** 2))]
        rows.append(row)
        print(f"{seed:4d} {loop['lag_px']:12.2f} | {res.summary.get('scan_lag_px') or 0.0:12.2f} "
              f"{res.summary.get('imprint_shift_px') or float('nan'):9.2f} {row[0]:14.1f} {row[1]:10.1f} {row[2]:12.1f} "
              f"{row[3]:15.1f} | {row[4]:22.1f} {row[5]:12.1f}", flush=True)
    c = np.array(rows)
    print(f"through the loop: centre RMS within 15 nm {np.mean(c[:, 0] <= 15) * 100:.0f} %, diameter RMS within 20 nm "
          f"{np.mean(c[:, 2] <= 20) * 100:.0f} %; medians {np.median(c[:, 0]):.1f} / {np.median(c[:, 2]):.1f} nm; "
          f"worst |x bias| {np.abs(c[:, 1]).max():.1f} nm. Without it: {np.mean(c[:, 4] <= 15) * 100:.0f} % / "
          f"{np.mean(c[:, 5] <= 20) * 100:.0f} %, medians {np.median(c[:, 4]):.1f} / {np.median(c[:, 5]):.1f} nm")


def _om_sweep(a, tmp):
    s0 = a.om_first_seed
    print(f"\nOM accuracy, seeds {s0}..{s0 + a.om_seeds - 1}, 512 x 512 at 0.1 µm")
    print("seed nominal bits  n missed false  centre_rms_nm  diam_rms_nm  diam_max_nm  t_s")
    allv = []
    times = []
    for i in range(a.om_seeds):
        seed = s0 + i
        nominal = a.om_nominal or [1.0, 2.0, 3.0][i % 3]
        r = render_om(seed, OmOptions(nominal_um=nominal, bits=[8, 16][i % 2]))
        path, spec = _files(tmp, r)
        t0 = time.perf_counter()
        res = run_indents([path], spec)
        dt = time.perf_counter() - t0
        times.append(dt)
        e, missed, false = _errors(res.indents, r.truth)
        allv.append(e)
        print(f"{seed} {r.truth['nominal_diameter_um']:5.1f} {r.truth['bits']:4d} {len(e):3d} {missed:4d} {false:5d} "
              f"{1000 * np.sqrt(np.mean(e[:, 0] ** 2)):12.1f} {1000 * np.sqrt(np.mean(e[:, 1] ** 2)):12.1f} "
              f"{1000 * np.abs(e[:, 1]).max():12.1f} {dt:6.1f}")
    e = np.vstack(allv)
    print(f"all {len(e)}: centre RMS {1000 * np.sqrt(np.mean(e[:, 0] ** 2)):.1f} nm (goal 20), diameter within "
          f"{1000 * np.abs(e[:, 1]).max():.0f} nm (goal 100), {np.mean(np.abs(e[:, 1]) <= 0.1) * 100:.0f} % within; "
          f"diameter RMS {1000 * np.sqrt(np.mean(e[:, 1] ** 2)):.1f} nm; run_indents per image: median "
          f"{np.median(times):.2f} s, max {max(times):.2f} s (goal <= 2 s)")


def _om_hard_sweep(a, tmp):
    """OM arrays drawn by the micrograph renderer (``grid``): 5 x 5 at 8 µm of 1, 2 or 3 µm imprints,
    480 x 480 at 0.1 µm; facet shading from light on one side, dark ridge and edge lines, pile-up
    halo, vignetting, texture, noise. Goals: every mean diagonal within ±50 nm, centre RMS <= 10 nm,
    image-wide centre bias <= 10 nm."""
    from markcal.fixtures.indent_micrograph import MicrographOptions, render_micrograph
    s0 = a.om_hard_first_seed
    sizes = [float(v) for v in a.om_hard_sizes.split(",")]
    optics = "Gaussian blur 1 px" if a.om_hard_na is None else f"Airy NA {a.om_hard_na}"
    print(f"\nhard OM arrays (micrograph renderer), seeds {s0}..{s0 + a.om_hard_seeds - 1}, 5 x 5 at 8 µm, "
          f"480 x 480 at 0.1 µm, {optics}, measured with objective NA {a.om_hard_objective_na or 'fitted'}"
          + (f", halo and crease from a {a.om_hard_reference_um:g} µm reference array (seed + 100)" if a.om_hard_reference_um else "")
          + "; goals: d within ±50 nm, centre RMS <= 10 nm, image bias <= 10 nm; "
          f"load {' '.join(f'{v:.1f}' for v in os.getloadavg())}")
    print("seed nominal  n missed  centre_rms_nm  bias_x_nm  bias_y_nm  d_err_mean_nm  d_err_max_nm  cpu_s")
    allv, worst_bias = [], 0.0
    for i in range(a.om_hard_seeds):
        seed = s0 + i
        nominal = sizes[i % len(sizes)]
        r = render_micrograph(seed, MicrographOptions(rows=480, cols=480, grid=(5, 5, 8.0), d_um=nominal,
                                                      na=a.om_hard_na))
        path = os.path.join(tmp, "om_hard.tif")
        with open(path, "wb") as fh:
            fh.write(tiff_bytes(r.data, r.pixel_um))
        spec = os.path.join(tmp, "om_hard.toml")
        with open(spec, "w") as fh:
            fh.write(array_toml(5, 5, 8.0, nominal))
        ref = None
        if a.om_hard_reference_um:
            rr = render_micrograph(seed + 100, MicrographOptions(rows=480, cols=480, grid=(5, 5, 8.0),
                                                                 d_um=a.om_hard_reference_um, na=a.om_hard_na))
            ref = os.path.join(tmp, "om_hard_reference.tif")
            with open(ref, "wb") as fh:
                fh.write(tiff_bytes(rr.data, rr.pixel_um))
        opts = IndentsOptions(kind="om", objective_na=a.om_hard_objective_na, optics_from=ref)
        c0 = time.process_time()
        f = measure_file(path, read_array_spec(spec), opts, held=optics_reference(ref, opts) if ref else None)
        cpu = time.process_time() - c0
        t = f.table
        e = []
        for ti in r.truth["imprints"]:
            k = int(np.argmin(np.hypot(t["x_um"] - ti["x_um"], t["y_um"] - ti["y_um"])))
            e.append((t["x_um"][k] - ti["x_um"], t["y_um"][k] - ti["y_um"], t["diameter_um"][k] - ti["d_um"]))
        e = 1000 * np.array(e)
        allv.append(e)
        bias = e[:, :2].mean(axis=0)
        worst_bias = max(worst_bias, float(np.hypot(*bias)))
        print(f"{seed} {nominal:5.1f} {len(t['x_um']):3d} {25 - len(t['x_um']):4d} "
              f"{np.sqrt(np.mean(e[:, 0] ** 2 + e[:, 1] ** 2)):12.1f} {bias[0]:+10.1f} {bias[1]:+10.1f} "
              f"{e[:, 2].mean():+13.1f} {np.abs(e[:, 2]).max():13.1f} {cpu:6.2f}", flush=True)
    e = np.vstack(allv)
    print(f"all {len(e)}: centre RMS {np.sqrt(np.mean(e[:, 0] ** 2 + e[:, 1] ** 2)):.1f} nm (goal 10), worst image "
          f"bias {worst_bias:.1f} nm (goal 10), d error mean {e[:, 2].mean():+.1f} nm, max |{np.abs(e[:, 2]).max():.1f}| nm, "
          f"{100 * np.mean(np.abs(e[:, 2]) <= 50):.0f} % within ±50 nm (goal 100 %)")


if __name__ == "__main__":
    main()
