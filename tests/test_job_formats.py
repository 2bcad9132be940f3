"""Job formats: DXF, SVG, HPGL and G-code read against their truth, ordered and written back."""
import json
import re
from collections import Counter

import numpy as np
import pytest

from markcal.fixtures.path_jobs import FILE_FORMATS, job_file
from markcal.pipeline.cli import main
from markcal.pipeline.flows.path import read_job
from markcal.stages.path_job import input_tour, jump_lengths_mm
from realdata import realdata_root

EXT = {"dxf": ".dxf", "svg": ".svg", "hpgl": ".plt", "gcode": ".gcode"}
TOL_MM = 0.01


realdata = realdata_root


def key(kind, xy, q=1e-6):
    """Stroke identity: an open stroke either way, a contour from any vertex but the same way round."""
    rows = [tuple(r) for r in np.round(np.asarray(xy, float).reshape(-1, 2) / q).astype(np.int64).tolist()]
    if kind == "polyline":
        rows = min(rows, rows[::-1])
    elif kind == "contour":
        k = rows.index(min(rows))
        rows = rows[k:] + rows[:k]
    return kind, tuple(rows)


def keys(job):
    return Counter(key(s.kind, s.xy_mm) for s in job.strokes)


def _forms(kind, p):
    """The vertex sequences a stroke may be written as: open strokes either way, contours from any
    vertex but the same way round."""
    p = np.asarray(p, float)
    if kind == "polyline":
        return [p, p[::-1]]
    if kind == "contour":
        return [np.roll(p, -k, axis=0) for k in range(len(p))]
    return [p]


def assert_same_strokes(ja, jb, atol=1e-6):
    """Every stroke of ``jb`` is a stroke of ``ja`` (each used once) within ``atol`` mm."""
    assert ja.n == jb.n
    free = list(range(ja.n))
    for s in jb.strokes:
        for j in free:
            t = ja.strokes[j]
            if t.kind == s.kind and len(t.xy_mm) == len(s.xy_mm) and any(
                    np.allclose(f, s.xy_mm, rtol=0, atol=atol) for f in _forms(t.kind, t.xy_mm)):
                free.remove(j)
                break
        else:
            raise AssertionError(f"stroke {s.kind} starting {s.xy_mm[0]} is not in the source job")


def write(tmp_path, fmt, seed=0):
    data, truth = job_file(fmt, seed)
    f = tmp_path / f"job{EXT[fmt]}"
    f.write_bytes(data)
    return f, truth


def run(argv, capsys):
    code = main(argv)
    return code, capsys.readouterr()


@pytest.mark.parametrize("fmt", FILE_FORMATS)
def test_reader_against_truth(tmp_path, fmt):
    f, truth = write(tmp_path, fmt, seed=3)
    jf = read_job(f, TOL_MM)
    assert jf.fmt == fmt
    got = keys(jf.job)
    want = Counter([key("polyline", p) for p in truth["lines"]] + [key("contour", p) for p in truth["contours"]] +
                   [key("point", p) for p in truth["points"]])
    assert not want - got, f"missing strokes: {want - got}"
    rest = [s for s in jf.job.strokes if key(s.kind, s.xy_mm) not in want]
    assert len(rest) == len(truth["circles"])
    for c, r in truth["circles"]:
        # one contour lies on this circle; its chords stray at most the tolerance and not needlessly less
        hit = [s for s in rest if s.kind == "contour" and np.allclose(np.hypot(*(s.xy_mm - c).T), r, atol=1e-7)]
        assert len(hit) == 1, (c, r)
        p = hit[0].xy_mm
        step = np.hypot(*(np.roll(p, -1, 0) - p).T)
        sagitta = r - np.sqrt(r * r - (step / 2) ** 2)
        assert sagitta.max() <= TOL_MM + 1e-9
        assert len(p) <= 2 * np.ceil(np.pi / np.arccos(1 - TOL_MM / r)) + 2
    assert Counter(jf.groups) == Counter(truth["groups"])
    assert jf.unsupported == truth["unsupported"]


@pytest.mark.parametrize("fmt", FILE_FORMATS)
def test_ordered_job_written_back(tmp_path, capsys, fmt):
    f, truth = write(tmp_path, fmt, seed=1)
    out = tmp_path / "o"
    code, cap = run(["path", str(f), "--out", str(out), "--kicks-per-stroke", "0", "--no-report"], capsys)
    assert code == 0, cap.err
    if truth["unsupported"]:
        assert "unsupported" in cap.err and next(iter(truth["unsupported"])) in cap.err
    s = json.loads((out / "summary.json").read_text())
    assert s["format"] == fmt and s["method"] == "auto" and s["method_used"] == "ls"
    assert s["unsupported"] == truth["unsupported"]
    assert s["jump_length_mm"] < s["input_jump_length_mm"]           # the order did change
    src = read_job(f, TOL_MM)
    back = read_job(out / f"ordered{EXT[fmt]}", TOL_MM)
    assert_same_strokes(src.job, back.job)                           # same strokes, contours the same way round
    assert back.unsupported == src.unsupported                        # non-geometric content kept
    jl = jump_lengths_mm(back.job, input_tour(back.job)).sum()
    assert jl == pytest.approx(s["jump_length_mm"], rel=1e-9, abs=1e-6)
    doc = json.loads((out / "ordered.json").read_text())
    assert sorted(st["source_index"] for st in doc["strokes"]) == list(range(s["n_strokes"]))


def test_dxf_written_keeps_layers_text_and_layer_order(tmp_path, capsys):
    import ezdxf
    f, truth = write(tmp_path, "dxf", seed=2)
    out = tmp_path / "o"
    code, cap = run(["path", str(f), "--out", str(out), "--kicks-per-stroke", "0", "--no-report",
                     "--keep-layer-order", "--quiet"], capsys)
    assert code == 0, cap.err
    doc = ezdxf.readfile(out / "ordered.dxf")
    assert doc.header["$INSUNITS"] == 1 and {"CUT", "MARK"} <= {ly.dxf.name for ly in doc.layers}
    assert len(doc.modelspace().query("TEXT")) == 1
    back = read_job(out / "ordered.dxf", TOL_MM)
    runs = [g for k, g in enumerate(back.groups) if k == 0 or back.groups[k - 1] != g]
    assert runs == ["CUT", "MARK"]                                    # each layer marked in one go, input order
    s = json.loads((out / "summary.json").read_text())
    assert s["keep_layer_order"] and s["n_groups"] == 2
    assert jump_lengths_mm(back.job, input_tour(back.job)).sum() == pytest.approx(s["jump_length_mm"], rel=1e-9)


_MOVE = re.compile(r"^G0?([01])\s*X([-\d.]+)\s*Y([-\d.]+)(?:\s*F[\d.]+)?\s*$")


def _gcode_lengths(text):
    """Independent reading of a G0/G1 job: (marked length, sorted non-XY lines), mm."""
    x = y = 0.0
    cut = 0.0
    other = []
    for line in text.splitlines():
        m = _MOVE.match(line.strip())
        if not m:
            other.append(line.strip())
            continue
        nx, ny = float(m.group(2)), float(m.group(3))
        if m.group(1) == "1":
            cut += np.hypot(nx - x, ny - y)
        x, y = nx, ny
    return cut, sorted(o for o in other if o)


def test_real_gcode_job(tmp_path, capsys):
    f = realdata() / "jobs" / "iso.gcode"
    if not f.exists():
        pytest.skip(f"real G-code job not found ({f})")
    jf = read_job(f, TOL_MM)
    text = f.read_text()
    cut, other = _gcode_lengths(text)
    assert jf.job.mark_length_mm == pytest.approx(cut, rel=1e-9)
    out = tmp_path / "o"
    code, cap = run(["path", str(f), "--out", str(out), "--kicks-per-stroke", "0", "--no-report", "--quiet"],
                    capsys)
    assert code == 0, cap.err
    s = json.loads((out / "summary.json").read_text())
    written = (out / "ordered.gcode").read_text()
    cut2, other2 = _gcode_lengths(written)
    assert cut2 == pytest.approx(cut, rel=1e-9)
    assert other2 == other                                            # every Z, M, F, G4 line kept
    back = read_job(out / "ordered.gcode", TOL_MM)
    assert_same_strokes(jf.job, back.job)
    assert jump_lengths_mm(back.job, input_tour(back.job)).sum() == pytest.approx(s["jump_length_mm"], rel=1e-9)
    assert s["jump_length_mm"] < 0.8 * s["input_jump_length_mm"]


def _dxf_bytes(units=4, text_only=False):
    import io

    import ezdxf
    doc = ezdxf.new()
    doc.header["$INSUNITS"] = units
    msp = doc.modelspace()
    msp.add_text("A")
    if not text_only:
        msp.add_line((0, 0), (1, 1))
    buf = io.StringIO()
    doc.write(buf)
    return buf.getvalue().encode()


def _bad_cases():
    dxf = job_file("dxf", 0)[0]
    svg = job_file("svg", 0)[0]
    return [
        ("trunc.dxf", dxf[: len(dxf) // 2], ["dxf"]),
        ("km.dxf", _dxf_bytes(units=7), ["unsupported units"]),
        ("text.dxf", _dxf_bytes(text_only=True), ["no geometry"]),
        ("trunc.svg", svg[: len(svg) // 2], ["svg"]),
        ("pct.svg", svg.replace(b'width="60mm"', b'width="50%"'), ["unsupported units"]),
        ("odd.plt", b"IN;SP1;PU0,0;PD100,100,200;", ["odd number"]),
        ("sc.plt", b"IN;SC0,100,0,100;PD10,10;", ["unsupported units"]),
        ("nolaser.gcode", b"G21\nG90\nG0 X0 Y0\nG1 X10 Y0\nG1 X10 Y10\n", ["laser-on", "m3"]),
        ("nomove.gcode", b"G21\nG90\nM3 S100\n", ["no geometry"]),
        ("bin.nc", b"\x00\x01\x02G1 X1", ["not a text"]),
        ("garbage.gcode", b"G21\nM3\nG1 X1 Y#2\n", ["line 3"]),
    ]


@pytest.mark.parametrize("name,data,words", _bad_cases(), ids=[c[0] for c in _bad_cases()])
def test_bad_job_files(tmp_path, capsys, name, data, words):
    f = tmp_path / name
    f.write_bytes(data)
    out = tmp_path / "o"
    code, cap = run(["path", str(f), "--out", str(out), "--quiet"], capsys)
    assert code == 1
    lines = cap.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("markcal: error:") and str(f) in lines[0], cap.err
    assert all(w in lines[0].lower() for w in words), lines[0]
    assert not (out / "summary.json").exists()
