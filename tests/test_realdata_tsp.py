"""Every TSPLIB instance in ../shared/realdata/tsp read and checked against its published optimum.

The optima (realdata README, TSPLIB): no tour may be shorter than the proven optimum, so a reader or
distance bug that shrinks the board shows here; the nearest-neighbour tour of a drilling board lies
within 10-30 % above it (a loose upper bound, so a scrambled reading shows too); the shipped optimal
tours reproduce the optimum exactly.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from markcal.fixtures.tsp_boards import read_tsplib, tsplib_length
from markcal.stages.path_job import make_job
from markcal.stages.path_tour import nearest_neighbour_tour

OPTIMA = {"pcb442": 50778, "d493": 35002, "rat783": 8806, "pr1002": 259045, "u1060": 224094, "pcb1173": 56892}


def _realdata() -> Path:
    env = os.environ.get("MARKCAL_REALDATA")
    for p in (env, Path(__file__).resolve().parents[1] / ".." / "shared" / "realdata", "/work/shared/realdata"):
        if p and (Path(p) / "tsp").is_dir():
            return Path(p)
    pytest.skip("real data folder not found (../shared/realdata; set MARKCAL_REALDATA)")


@pytest.mark.parametrize("name", sorted(OPTIMA))
def test_instance_read_and_bounded_by_its_optimum(name):
    path = _realdata() / "tsp" / f"{name}.tsp"
    xy = read_tsplib(path)
    n = int(next(l.split(":")[1] for l in path.read_text().splitlines() if l.upper().startswith("DIMENSION")))
    assert xy.shape == (n, 2) and np.isfinite(xy).all() and len(np.unique(xy, axis=0)) > 0.9 * n
    job = make_job([("point", p) for p in xy])
    tour = nearest_neighbour_tour(job)
    length = tsplib_length(xy, np.asarray(tour.order))
    assert OPTIMA[name] <= length <= 1.35 * OPTIMA[name], (name, length)


@pytest.mark.parametrize("name", ["pcb442", "pr1002"])
def test_shipped_optimal_tours_reproduce_the_optimum(name):
    root = _realdata() / "tsp"
    xy = read_tsplib(root / f"{name}.tsp")
    text = (root / f"{name}.opt.tour").read_text().split("TOUR_SECTION")[1]
    order = np.array([int(v) for v in text.split() if v.lstrip("-").isdigit() and int(v) > 0], int) - 1
    assert sorted(order.tolist()) == list(range(len(xy)))
    assert tsplib_length(xy, order) == OPTIMA[name]
