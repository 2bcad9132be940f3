"""Path flow: tours against known optima, the paper's GA operators, the CLI and bad input."""
import json
import os

import numpy as np
import pytest

from markcal.fixtures.path_jobs import fiducial_grid, paper_points, text_job
from markcal.pipeline.cli import main
from markcal.stages.errors import MarkcalError
from markcal.stages.path_ga import GAOptions, order_crossover, run_ga
from markcal.stages.path_job import Timing, Tour, check_tour, input_tour, make_job, tour_cost
from markcal.stages.path_tour import LocalSearchOptions, best_entries, local_search, nearest_neighbour_tour, \
    population_arrays, population_cost, raster_tour

TM = Timing()


def held_karp(p):
    """Exact closed-tour length of a few points (dynamic programming)."""
    n = len(p)
    d = np.hypot(*(p[:, None] - p[None]).transpose(2, 0, 1))
    full = 1 << (n - 1)
    dp = np.full((full, n), np.inf)
    for j in range(1, n):
        dp[1 << (j - 1), j] = d[0, j]
    for s in range(1, full):
        for j in range(1, n):
            if not s & (1 << (j - 1)) or not np.isfinite(dp[s, j]):
                continue
            for k in range(1, n):
                if s & (1 << (k - 1)):
                    continue
                t = s | (1 << (k - 1))
                dp[t, k] = min(dp[t, k], dp[s, j] + d[j, k])
    return min(dp[full - 1, j] + d[j, 0] for j in range(1, n))


def points_job(p):
    return make_job(("point", q) for q in p)


def lattice(m, seed, pitch=1.0):
    """m x m lattice (m even) in random order: the optimal closed tour is m^2 * pitch."""
    g = np.stack(np.meshgrid(np.arange(m), np.arange(m)), -1).reshape(-1, 2) * pitch
    return g[np.random.default_rng(seed).permutation(len(g))]


# ----------------------------------------------------------------------------- local search

@pytest.mark.parametrize("seed", [0, 1, 2])
def test_local_search_exact_on_small_random(seed):
    p = np.random.default_rng(seed).random((10, 2)) * 50
    job = points_job(p)
    t = local_search(job, nearest_neighbour_tour(job), TM, LocalSearchOptions(seed=seed))
    check_tour(job, t)
    assert tour_cost(job, t, TM) == pytest.approx(held_karp(p), rel=1e-9)


def test_local_search_lattice_and_circle_within_half_percent():
    job = points_job(lattice(10, 5, pitch=2.0))           # optimum 200 mm
    t = local_search(job, nearest_neighbour_tour(job), TM)
    assert tour_cost(job, t, TM) <= 200.0 * 1.005
    ang = np.random.default_rng(3).permutation(90) * 2 * np.pi / 90
    job = points_job(np.column_stack([np.cos(ang), np.sin(ang)]) * 30)   # optimum: the polygon
    opt = 90 * 2 * 30 * np.sin(np.pi / 90)
    t = local_search(job, input_tour(job), TM)
    assert tour_cost(job, t, TM) == pytest.approx(opt, rel=1e-9)


def test_open_strokes_are_turned_round():
    # 8 vertical lines all drawn upwards: the best tour runs every other one down
    k = 8
    job = make_job(("polyline", [(i, 0.0), (i, 10.0)]) for i in np.random.default_rng(1).permutation(k))
    t = local_search(job, input_tour(job), TM)
    assert tour_cost(job, t, TM) == pytest.approx(2.0 * (k - 1), abs=1e-9)
    assert t.reverse.sum() == k // 2
    assert tour_cost(job, input_tour(job), TM) > 4 * tour_cost(job, t, TM)


def test_contours_entered_at_best_vertex():
    job = fiducial_grid(4, spec=__import__("markcal.stages.plate", fromlist=["PlateSpec"]).PlateSpec(rows=4, cols=4))
    nn = nearest_neighbour_tour(job)
    t = local_search(job, nn, TM)
    check_tour(job, t)
    # no single contour can be re-entered more cheaply
    again = best_entries(job, t, TM)
    assert tour_cost(job, again, TM) == pytest.approx(tour_cost(job, t, TM), abs=1e-9)
    # 16 fiducials 10.56 mm apart, rings 2.5 / 2.7 mm: the jumps between fiducials are at least
    # pitch - 2 x 2.7 mm, and the two rings of one fiducial are 0.2 mm apart
    pitch = 190.0 / 18.0
    lower = 16 * (pitch - 5.4) + 16 * 0.2
    assert lower <= tour_cost(job, t, TM) <= 16 * pitch
    assert tour_cost(job, t, TM) < 0.5 * tour_cost(job, input_tour(job), TM)


def test_time_metric_counts_settle_per_jump():
    tm = Timing(metric="time", jump_speed_mm_s=1000.0, settle_s=1e-3)
    job = points_job(lattice(4, 2, pitch=1.0))     # optimum 16 mm in 16 jumps
    t = local_search(job, input_tour(job), tm)
    assert tour_cost(job, t, tm) == pytest.approx(16 / 1000.0 + 16 * 1e-3, rel=1e-9)


def test_raster_rows_of_a_grid():
    job = points_job(lattice(6, 1))
    t = raster_tour(job)
    # serpentine over 6 rows: 5 steps per row, 5 row changes, and back from the last row end
    assert tour_cost(job, t, TM) == pytest.approx(6 * 5 + 5 + np.hypot(0, 5), abs=1e-9)


# ----------------------------------------------------------------------------- GA

def test_order_crossover_keeps_segment_and_parent2_order():
    p1 = np.array([1, 2, 3, 4, 5, 6, 7, 8, 9])
    p2 = np.array([9, -3, 7, 8, 2, 6, 5, 1, 4])
    c = order_crossover(p1, p2, 3, 5)
    assert list(c[3:6]) == [4, 5, 6]
    # the rest from p2 in order starting after the second cut, signs carried over
    assert list(c) == [7, 8, 2, 4, 5, 6, 1, 9, -3]
    assert sorted(np.abs(c)) == list(range(1, 10))


def test_population_cost_matches_tour_cost():
    job = text_job(0, lines=("MARKCAL 0.8", "A-B/D"))
    arr = population_arrays(job)
    rng = np.random.default_rng(0)
    g = np.array([rng.permutation(job.n) + 1 for _ in range(6)]) * rng.choice([-1, 1], (6, job.n))
    from markcal.stages.path_ga import genes_to_tour
    vec = population_cost(g, arr, TM)
    one = [tour_cost(job, genes_to_tour(row, job, arr, TM), TM) for row in g]
    assert np.allclose(vec, one, rtol=1e-12)


def test_paper_ga_on_a_lattice_and_ga_plus_local_search():
    job = points_job(lattice(8, 7, pitch=2.5))          # optimum 160 mm
    opt = GAOptions(generations=2500, seed=3)
    r = run_ga(job, TM, opt)
    check_tour(job, r.tour)
    assert r.cost == pytest.approx(tour_cost(job, r.tour, TM), rel=1e-12)
    assert np.all(np.diff(r.curve) <= 1e-9)                    # elitism: the best never gets worse
    assert r.curve[0] > 2.5 * r.cost                            # it converged from the random start
    assert r.cost <= 160.0 * 1.25                               # the paper GA: within 25 %
    better = local_search(job, r.tour, TM)
    assert tour_cost(job, better, TM) <= 160.0 * 1.005
    again = run_ga(job, TM, opt)
    assert np.array_equal(again.tour.order, r.tour.order) and again.cost == r.cost


# ----------------------------------------------------------------------------- CLI

def _run(argv, capsys):
    code = main(argv)
    return code, capsys.readouterr()


def test_cli_csv_points_end_to_end(tmp_path, capsys):
    code, _ = _run(["render", "path", "--kind", "paper", "--seed", "4", "--out", str(tmp_path / "j"), "--quiet"],
                   capsys)
    assert code == 0
    job_csv = tmp_path / "j" / "job.csv"
    out = tmp_path / "o"
    code, cap = _run(["path", str(job_csv), "--out", str(out), "--method", "ga+ls", "--generations", "300",
                      "--quiet"], capsys)
    assert code == 0, cap.err
    assert cap.out.strip().endswith("report.html")
    s = json.loads((out / "summary.json").read_text())
    for k in ("input_jump_length_mm", "raster_jump_length_mm", "nn_jump_length_mm", "ga_jump_length_mm",
              "ga_ls_jump_length_mm", "jump_length_mm", "time_s", "runtime_s", "method_used"):
        assert k in s
    assert s["method_used"] == "ga+ls"
    assert s["jump_length_mm"] <= s["ga_jump_length_mm"] + 1e-9
    assert s["jump_length_mm"] < s["nn_jump_length_mm"] and s["jump_length_mm"] < s["raster_jump_length_mm"]
    rows_in = job_csv.read_text().splitlines()
    rows_out = (out / "ordered.csv").read_text().splitlines()
    assert rows_out[0] == "x_mm,y_mm" and sorted(rows_out[1:]) == sorted(rows_in[1:])
    p = np.array([[float(v) for v in r.split(",")] for r in rows_out[1:]])
    assert np.hypot(*(np.roll(p, -1, 0) - p).T).sum() == pytest.approx(s["jump_length_mm"], rel=1e-9)
    html = (out / "report.html").read_text()
    assert "GA convergence" in html and "data:image/png;base64" in html and "http" not in html.split("<body>")[1]


def test_cli_json_text_job_round_trip(tmp_path, capsys):
    code, _ = _run(["render", "path", "--kind", "text", "--out", str(tmp_path / "j"), "--quiet"], capsys)
    assert code == 0
    out = tmp_path / "o"
    code, cap = _run(["path", str(tmp_path / "j" / "job.json"), "--out", str(out), "--method", "ls", "--quiet"],
                     capsys)
    assert code == 0, cap.err
    s = json.loads((out / "summary.json").read_text())
    doc = json.loads((out / "ordered.json").read_text())
    assert sorted(st["source_index"] for st in doc["strokes"]) == list(range(s["n_strokes"]))
    assert any(st.get("reversed") for st in doc["strokes"])
    # the ordered job, marked as written, has the optimised jump length
    code, cap = _run(["path", str(out / "ordered.json"), "--out", str(tmp_path / "o2"), "--method", "input",
                      "--no-report", "--quiet"], capsys)
    assert code == 0, cap.err
    s2 = json.loads((tmp_path / "o2" / "summary.json").read_text())
    assert s2["jump_length_mm"] == pytest.approx(s["jump_length_mm"], rel=1e-9)
    assert s["length_reduction_vs_input_pct"] > 40


def test_duplicates_kept_and_said(tmp_path, capsys):
    job = tmp_path / "dup.json"
    strokes = [{"kind": "polyline", "xy_mm": [[0, 0], [5, 0]]}, {"kind": "point", "xy_mm": [3, 3]},
               {"kind": "polyline", "xy_mm": [[5, 0], [0, 0]]}, {"kind": "contour", "xy_mm": [[9, 9], [10, 9], [10, 10]]},
               {"kind": "point", "xy_mm": [8, 1]}]
    job.write_text(json.dumps({"units": "mm", "strokes": strokes}))
    code, cap = _run(["path", str(job), "--out", str(tmp_path / "o"), "--kicks-per-stroke", "0"], capsys)
    assert code == 0
    assert "duplicate" in cap.err
    s = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert s["n_duplicate_strokes"] == 1 and s["duplicate_strokes"] == [[0, 2]]
    assert len(json.loads((tmp_path / "o" / "ordered.json").read_text())["strokes"]) == 5


def test_too_large_for_ga_falls_back(tmp_path, capsys):
    job = tmp_path / "p.csv"
    p = np.random.default_rng(0).random((40, 2)) * 10
    job.write_text("id,x_mm,y_mm\n" + "".join(f"a{i},{x},{y}\n" for i, (x, y) in enumerate(p)))
    code, cap = _run(["path", str(job), "--out", str(tmp_path / "o"), "--method", "ga", "--ga-max-strokes", "30"],
                     capsys)
    assert code == 0
    assert "fell back to local search" in cap.err
    s = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert s["method"] == "ga" and s["method_used"] == "ls" and s["fallback"] is True
    assert (tmp_path / "o" / "ordered.csv").read_text().splitlines()[0] == "id,x_mm,y_mm"


@pytest.mark.parametrize("name,text,words", [
    ("empty.json", "", ["empty", "no strokes"]),
    ("none.json", '{"strokes": []}', ["no strokes"]),
    ("empty.csv", "x_mm,y_mm\n", ["no strokes"]),
    ("nan.csv", "x_mm,y_mm\n1,2\nnan,3\n4,5\n", ["nan"]),
    ("nan.json", '{"strokes": [{"kind": "polyline", "xy_mm": [[0, 0], [NaN, 1]]}]}', ["nan"]),
    ("short.json", '{"strokes": [{"kind": "point", "xy_mm": [0, 0]}, {"kind": "polyline", "xy_mm": [[0, 0]]}]}',
     ["at least 2"]),
    ("tri.json", '{"strokes": [{"kind": "contour", "xy_mm": [[0, 0], [1, 0], [0, 0]]}]}', ["at least 3"]),
    ("key.json", '{"strokes": [], "stroke": []}', ["unknown key"]),
    ("head.csv", "x,y\n1,2\n", ["x_mm"]),
])
def test_bad_input(tmp_path, capsys, name, text, words):
    f = tmp_path / name
    f.write_text(text)
    out = tmp_path / "o"
    code, cap = _run(["path", str(f), "--out", str(out), "--quiet"], capsys)
    assert code == 1
    lines = cap.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("markcal: error:") and str(f) in lines[0], cap.err
    assert any(w in lines[0].lower() for w in words), lines[0]
    assert not (out / "summary.json").exists()


def test_make_job_errors_name_the_stroke():
    with pytest.raises(MarkcalError, match="stroke 1"):
        make_job([("point", (0, 0)), ("polyline", [(0, 0)])])
    with pytest.raises(MarkcalError, match="no strokes"):
        make_job([])
