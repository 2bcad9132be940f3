"""Iterative solvers refuse non-finite input before iterating, and their caps hold (issue 17; the table of
solvers and caps is docs/solver_caps.md)."""
from __future__ import annotations

import numpy as np
import pytest

from markcal.stages.errors import MarkcalError


def _grid_mm():
    g = np.array([(x, y) for x in (-20.0, -10.0, 0.0, 10.0, 20.0) for y in (-20.0, -10.0, 0.0, 10.0, 20.0)])
    return g, g * 1.001


def test_galvo_fit_refuses_nan_landing():
    from markcal.stages.galvo_fit import fit_physical
    cmd, land = _grid_mm()
    fit_physical(cmd, land, 300.0, 15.0)                         # finite: fits
    land[3, 1] = np.nan
    with pytest.raises(MarkcalError, match="land_mm is not finite"):
        fit_physical(cmd, land, 300.0, 15.0)


def test_galvo_fit_has_an_evaluation_cap():
    from markcal.stages import galvo_fit
    assert 0 < galvo_fit.MAX_NFEV <= 10_000


def test_plane_fit_refuses_inf_points():
    from markcal.stages.plane import fit_plane
    rng = np.random.default_rng(0)
    xyz = np.column_stack([rng.uniform(-40, 40, 2000), rng.uniform(-40, 40, 2000), rng.normal(0, 0.01, 2000)])
    assert abs(fit_plane(xyz).normal[2]) > 0.999                  # finite: the z axis
    xyz[17, 2] = np.inf
    with pytest.raises(MarkcalError, match="xyz_mm is not finite"):
        fit_plane(xyz)


def test_path_local_search_refuses_nan_coordinates():
    from markcal.stages.path_job import Job, Stroke, Timing
    from markcal.stages.path_tour import local_search, nearest_neighbour_tour
    pts = [np.array([[float(k % 5), float(k // 5)]]) for k in range(12)]
    pts[7] = np.array([[np.nan, 1.0]])
    job = Job(tuple(Stroke("point", p) for p in pts))
    with pytest.raises(MarkcalError, match="xy_mm is not finite"):
        local_search(job, nearest_neighbour_tour(job), Timing())


@pytest.mark.parametrize("key,value,needle", [("generations", 10 ** 9, "at most 1,000,000"),
                                              ("population", 10 ** 6, "at most 10,000")])
def test_path_ga_caps(key, value, needle):
    from markcal.pipeline.flows.path import FLOW
    with pytest.raises(MarkcalError, match=needle):
        FLOW.check_options({key: value})
