"""Time and memory of markcal refusing the heaviest hostile inputs of issue 17 (goal: < 5 s, < 1 GiB each).

Each case runs as a fresh ``python -m markcal.pipeline.cli`` process (start-up included) under
RLIMIT_AS = 1.5 GiB; printed: exit status, stderr lines, wall s, CPU s, peak RSS MiB, the load average.

    python benchmarks/hostile_cases.py
"""
from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np

AS_LIMIT = 3 * 2 ** 29


def _limit():
    resource.setrlimit(resource.RLIMIT_AS, (AS_LIMIT, AS_LIMIT))


def cases(d: str) -> dict:
    plate = os.path.join(d, "plate.toml")
    with open(plate, "w") as fh:
        fh.write("[grid]\nrows = 7\ncols = 7\npitch_mm = 10.0\n")
    ply = os.path.join(d, "faces.ply")
    with open(ply, "wb") as fh:
        fh.write(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                 b"property float z\nproperty float intensity\nelement face 1000000000\n"
                 b"property list uchar int vertex_indices\nend_header\n" + bytes(11_000_000))
    import tifffile
    tif = os.path.join(d, "bomb.tif")
    tifffile.imwrite(tif, np.zeros((16000, 16000), np.uint8), compression="zlib", tile=(1024, 1024))
    job = os.path.join(d, "deep.json")
    with open(job, "w") as fh:
        fh.write("[" * 100_000 + "]" * 100_000)
    big = os.path.join(d, "big.json")
    with open(big, "w") as fh:
        json.dump({"strokes": [{"kind": "point", "xy_mm": [1e300, 0.0]}]}, fh)
    step = os.path.join(d, "step.toml")
    with open(step, "w") as fh:
        fh.write("[grid]\nrows = 7\ncols = 7\npitch_mm = 10.0\n[correction]\ngrid_step_mm = 1e-6\n")
    npy = os.path.join(d, "c.npy")
    a = np.random.default_rng(0).uniform(-40, 40, (2000, 4))
    a[:50, 2] = 1e300
    np.save(npy, a)
    sess = os.path.join(d, "pm")
    subprocess.run([sys.executable, "-m", "markcal.pipeline.cli", "render", "pmcal", "--pose-grid", "4", "--out",
                    sess, "--quiet"], check=True, stdout=subprocess.DEVNULL)
    lines = open(os.path.join(sess, "axes.csv")).read().splitlines()
    c = lines[2].split(",")
    c[1] = "1e308"
    lines[2] = ",".join(c)
    with open(os.path.join(sess, "axes.csv"), "w") as fh:
        fh.write("\n".join(lines) + "\n")
    new = _unseen_cases(d)
    o = os.path.join(d, "o")
    return {
        "PLY declaring 1e9 faces (11 MB)": ["scan", ply, "--plate", plate, "--out", o],
        "TIFF 16000² zlib bomb": ["indents", tif, "--pixel-size-um", "0.1", "--out", o],
        "path JSON 100000-deep": ["path", job, "--out", o],
        "path JSON coordinate 1e300": ["path", big, "--out", o],
        "plate grid_step_mm 1e-6": ["scan", npy, "--plate", step, "--out", o],
        "NPY cloud z = 1e300": ["scan", npy, "--plate", plate, "--out", o],
        "pmcal axes.csv 1e308": ["pmcal", sess, "--out", o],
        "drift --noise-um 1e300": ["drift", os.path.join(sess, "drift.csv"), "--noise-um", "1e300", "--out", o],
        **new,
    }


def _unseen_cases(d: str) -> dict:
    """The heaviest of tests/test_hostile_unseen.py (round 2 of issue 17)."""
    sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))
    import test_hostile_unseen as u
    o = os.path.join(d, "o")
    out = {}
    for label, table, key, cmd in (("TIFF declaring 50000² float32", u.TIFFS, "declared_2e9_pixels", "indents"),
                                   ("TIFF with an IFD loop", u.TIFFS, "ifd_loop", "indents")):
        p = os.path.join(d, f"{key}.tif")
        with open(p, "wb") as fh:
            fh.write(table[key])
        out[label] = [cmd, p, "--out", o]
    for label, key in (("SVG billion laughs", "svg_billion_laughs"), ("SVG <use> recursion", "svg_use_recursion"),
                       ("DXF circular block refs", "dxf_circular_blocks"), ("DXF HATCH of 1e8 vertices", "dxf_huge_hatch"),
                       ("G-code arc of 1e9 turns", "gcode_1e9_arcs"), ("G-code arc radius 1e12", "gcode_arc_huge_radius")):
        name, data = u.JOBS[key]
        p = os.path.join(d, key + os.path.splitext(name)[1])
        with open(p, "w") as fh:
            fh.write(data)
        out[label] = ["path", p, "--out", o]
    name, data = u.LOGS["time_step_1e-300"]
    p = os.path.join(d, "tiny_steps.csv")
    with open(p, "w") as fh:
        fh.write(data)
    out["servo log, steps of 1e-300 s"] = ["servo", "--trace", p, "--out", o]
    p = os.path.join(d, "huge_plate.toml")
    with open(p, "w") as fh:
        fh.write(u.PLATES["rows_cols_huge_field"])
    out["plate 1000 x 1000 at 1 m"] = ["scan", os.path.join(d, "c.npy"), "--plate", p, "--out", o]
    out["path --out /proc/self/x"] = ["path", os.path.join(d, "gcode_1e9_arcs.gcode"), "--out", "/proc/self/x"]
    return out


def main() -> None:
    with tempfile.TemporaryDirectory() as d:
        todo = cases(d)
        print(f"load average {os.getloadavg()[0]:.1f} (2 cores)")
        print(f"{'case':34s} {'exit':>4s} {'lines':>5s} {'wall s':>7s} {'CPU s':>6s} {'RSS MiB':>8s}")
        for name, argv in todo.items():
            with tempfile.TemporaryFile() as errf:
                t0 = time.perf_counter()
                p = subprocess.Popen([sys.executable, "-m", "markcal.pipeline.cli", *argv, "--quiet"],
                                     stdout=subprocess.DEVNULL, stderr=errf, preexec_fn=_limit)
                _, status, ru = os.wait4(p.pid, 0)
                wall = time.perf_counter() - t0
                errf.seek(0)
                err = errf.read().decode("utf-8", "replace").strip()
            print(f"{name:34s} {os.waitstatus_to_exitcode(status):4d} {len(err.splitlines()):5d} {wall:7.2f} "
                  f"{ru.ru_utime + ru.ru_stime:6.2f} {ru.ru_maxrss / 1024:8.0f}   …{err[-80:]}")


if __name__ == "__main__":
    main()
