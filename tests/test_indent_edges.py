"""stages/indent_edges.py: the edges drawn past chips, on boundaries whose areas are known in closed form."""
from __future__ import annotations

import numpy as np
import pytest

from markcal.stages.indent_edges import edges_past_chips, shoelace

PX_UM = 0.1
HALF_D_UM = 10.0
CENTRE = np.array([12.0, 12.0])
BUMP_HALF_LEN_UM, BUMP_OUT_UM = 2.0, 1.0        # a half-ellipse on edge 0: area pi / 2 * 2 * 1 um^2


def _diamond(bump: bool, bow=0.0, half_len=BUMP_HALF_LEN_UM, out=BUMP_OUT_UM, chipped=(0,)):
    """The closed boundary of a diamond of diagonals 2 x HALF_D_UM and its corners in order: every edge bowed out
    by 4 bow (d/2) t (1 - t) (negative: in; ``bow`` one for all or one per edge), the edges ``chipped`` (edge 0:
    corner 0 to 1) with a half-ellipse ``half_len`` long each way bulging ``out`` at their middle."""
    bows = np.broadcast_to(np.asarray(bow, float), (4,))
    corners = CENTRE + HALF_D_UM * np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
    pts = []
    for k in range(4):
        p0, p1 = corners[k], corners[(k + 1) % 4]
        ln = np.hypot(*(p1 - p0))
        e = (p1 - p0) / ln
        nrm = np.array([e[1], -e[0]])
        nrm = nrm if nrm @ ((p0 + p1) / 2 - CENTRE) > 0 else -nrm
        s = np.arange(0.0, ln, 0.02)
        u = (s - ln / 2) / half_len
        off = 4 * bows[k] * HALF_D_UM * (s / ln) * (1 - s / ln)
        if bump and k in chipped:
            off = off + out * np.sqrt(np.clip(1 - u * u, 0, 1))
        pts.append(p0 + np.outer(s, e) + np.outer(off, nrm))
    return np.vstack(pts), corners


def _heights(slope_nm_px):
    """A 240 x 240 window: flat (a chip's floor everywhere) or sloping as a facet does."""
    rr, cc = np.mgrid[0:240, 0:240].astype(float)
    return -100.0 + slope_nm_px * (rr + cc) / np.sqrt(2)


def test_chip_on_a_flat_floor_is_taken_back_onto_the_edge():
    c, corners = _diamond(bump=True)
    got = edges_past_chips(c, corners, PX_UM, 2 * HALF_D_UM, _heights(0.0), (0, 0), 10.0)
    bump_um2 = np.pi / 2 * BUMP_HALF_LEN_UM * BUMP_OUT_UM
    assert got.chipped_edges == (0,)
    assert got.chipped_area_um2 == pytest.approx(bump_um2, rel=0.03)
    assert shoelace(got.contour_um) == pytest.approx(2 * HALF_D_UM ** 2, rel=0.002)


def test_bulge_over_a_sloping_facet_is_no_chip():
    """The same bulge where the surface slopes as the facets do (a facet's own S-bend): left as it is."""
    c, corners = _diamond(bump=True)
    got = edges_past_chips(c, corners, PX_UM, 2 * HALF_D_UM, _heights(10.0), (0, 0), 10.0)
    assert got.chipped_edges == () and got.chipped_area_um2 == 0.0
    assert np.array_equal(got.contour_um, c)


@pytest.mark.parametrize("bow", [-0.08, 0.08])
def test_bowed_edges_without_chips_are_left_alone(bow):
    """Edges bowed in (sink-in) or out (pile-up) by 8 % of d/2, over a flat floor: no chip."""
    c, corners = _diamond(bump=False, bow=bow)
    got = edges_past_chips(c, corners, PX_UM, 2 * HALF_D_UM, _heights(0.0), (0, 0), 10.0)
    assert got.chipped_edges == () and np.array_equal(got.contour_um, c)


@pytest.mark.parametrize("bow", [-0.08, 0.08])
def test_chip_on_a_bowed_edge(bow):
    """The chip on an edge bowed by 8 % of d/2: taken back onto the bowed edge, not onto the chord."""
    c, corners = _diamond(bump=True, bow=bow)
    got = edges_past_chips(c, corners, PX_UM, 2 * HALF_D_UM, _heights(0.0), (0, 0), 10.0)
    whole, _ = _diamond(bump=False, bow=bow)
    assert got.chipped_edges == (0,)
    assert got.chipped_area_um2 == pytest.approx(shoelace(c) - shoelace(whole), rel=0.03)


def test_chips_along_half_of_two_edges():
    """Chips along half of two opposite edges (half-ellipses 7 µm long, 1 µm out) on edges sunk in by 5 % of d/2:
    the first curves follow the chips out (their middles 0.5 µm out; chipped area 0.6 of the truth); fitted again
    from the other edges' bow, both chips are found and the area is the sunk-in diamond's within 0.5 %."""
    kw = dict(bow=-0.05, half_len=3.5, out=1.0, chipped=(0, 2))
    c, corners = _diamond(bump=True, **kw)
    whole, _ = _diamond(bump=False, **kw)
    got = edges_past_chips(c, corners, PX_UM, 2 * HALF_D_UM, _heights(0.0), (0, 0), 10.0)
    assert got.chipped_edges == (0, 2)
    assert got.chipped_area_um2 == pytest.approx(shoelace(c) - shoelace(whole), rel=0.05)
    assert shoelace(got.contour_um) == pytest.approx(shoelace(whole), rel=0.005)


def test_pile_up_bow_on_two_edges_is_no_chip():
    """Two opposite edges bowed out (pile-up) and two in, over a facet's slope: the out-bowed edges are fitted again
    from the others' bow, but the region between is no shelf, so nothing is taken."""
    c, corners = _diamond(bump=False, bow=(0.08, -0.04, 0.08, -0.04))
    got = edges_past_chips(c, corners, PX_UM, 2 * HALF_D_UM, _heights(10.0), (0, 0), 10.0)
    assert got.chipped_edges == () and np.array_equal(got.contour_um, c)


def test_chip_on_an_edge_bowed_out_by_pile_up():
    """Edge 0 bowed out by 8 % of d/2 (pile-up) with a short chip on it, the others sunk in by 4 %; the surface
    slopes as a facet does but for the chip's flat floor. The chip is found beside the bowed curve and the bow
    is kept: only the chip's area is taken (within 5 %), not the band between the bow and its neighbours'."""
    bows = (0.08, -0.04, -0.04, -0.04)
    c, corners = _diamond(bump=True, bow=bows)
    whole, _ = _diamond(bump=False, bow=bows)
    # the chip's flat floor round the middle of edge 0 (its outward normal along (1, 1) / sqrt 2 here)
    mid = (corners[0] + corners[1]) / 2 + np.array([1.0, 1.0]) / np.sqrt(2) * (0.08 * HALF_D_UM + 0.5 * BUMP_OUT_UM)
    z = _heights(10.0)
    rr, cc = np.mgrid[0:240, 0:240]
    z[np.hypot(rr * PX_UM - mid[1], cc * PX_UM - mid[0]) < BUMP_HALF_LEN_UM + 0.3] = -150.0
    got = edges_past_chips(c, corners, PX_UM, 2 * HALF_D_UM, z, (0, 0), 10.0)
    assert got.chipped_edges == (0,)
    assert got.chipped_area_um2 == pytest.approx(shoelace(c) - shoelace(whole), rel=0.05)
