"""The original surface beyond the corners (stages/indent_level.corner_level, level_single's anchor).

Where one imprint fills most of the field, the far field left lies on the pile-up's tails. The pile-up of a
Vickers imprint vanishes at its corners, so strips along the diagonals beyond them hold the original surface.
Stage tests on a drawn surface with a known level; flow tests on the feedback renderer
(fixtures/indent_afm_feedback, written without our model), against its geometric truth.
"""
import itertools

import numpy as np
import pytest

from markcal.pipeline.flows.indents import IndentsOptions, run_indents
from markcal.stages.indent_level import CornerLevel, corner_level, level_single

N = 200
CENTRE = np.array([100.0, 100.0])
HALF_DIAG = 70.0


def _corners(theta_deg=20.0):
    t = np.radians(theta_deg + 90.0 * np.arange(4))
    return CENTRE + HALF_DIAG * np.column_stack([np.cos(t), np.sin(t)])


def _tails(theta_deg=20.0, amp_nm=40.0):
    """Pile-up's tails outside a circle of the half-diagonal: ``amp_nm`` sin^2(2 psi) decaying outwards, psi the
    angle from the nearest diagonal; nil on the diagonals."""
    rr, cc = np.mgrid[0:N, 0:N].astype(float)
    r = np.hypot(cc - CENTRE[0], rr - CENTRE[1])
    psi = np.arctan2(rr - CENTRE[1], cc - CENTRE[0]) - np.radians(theta_deg)
    return amp_nm * np.sin(2 * psi) ** 2 * np.exp(-np.maximum(r - HALF_DIAG, 0) / 40.0)


def test_strips_read_the_original_surface_under_a_crack():
    """The map's zero 15 nm above the original surface; one strip with a radial crack 80 nm deep and 3 px wide
    down its middle. Every strip reads -15 nm within 1 nm: the crack is left out, the tails beside it too."""
    rng = np.random.default_rng(0)
    z = _tails() - 15.0 + rng.normal(0, 0.5, (N, N))
    corners = _corners()
    e = (corners[1] - CENTRE) / HALF_DIAG
    rr, cc = np.mgrid[0:N, 0:N].astype(float)
    along = (cc - corners[1][0]) * e[0] + (rr - corners[1][1]) * e[1]
    across = -(cc - CENTRE[0]) * e[1] + (rr - CENTRE[1]) * e[0]
    z[(along > 0) & (np.abs(across) <= 1.5)] -= 80.0
    lev = corner_level(z, [corners], [CENTRE], [2 * HALF_DIAG], 0.5)
    assert len(lev.levels_nm) == 4
    assert np.all(np.abs(lev.levels_nm + 15.0) <= 1.0), lev.levels_nm
    assert lev.weight(0.5) == 1.0
    # the crack's pixels are not among the strips
    assert not (lev.strips & (along > 0) & (np.abs(across) <= 1.5)).any()


@pytest.mark.parametrize("levels,below", [((-8.0, -9.0, -7.5, -8.5), True),     # tails: clearly below
                                          ((-2.0, -2.5, -1.5, -2.2), False),    # under 3 nm
                                          ((6.0, 7.0, 5.0, 6.5), False),        # above: not tails
                                          ((-20.0, 12.0, -4.0, 9.0), False),    # scattered
                                          ((-9.0,), False)])                     # one strip
def test_levelled_to_the_strips_only_when_they_lie_clearly_below(levels, below):
    """The strips' level is taken only when it lies under the map's zero by more than 3 nm, 2 noise levels and
    twice the standard error of its spread, on two strips at least."""
    z = np.zeros((N, N))
    corners = _corners()
    for q, v in zip(corners, levels):
        e = (q - CENTRE) / HALF_DIAG
        rr, cc = np.mgrid[0:N, 0:N].astype(float)
        along = (cc - q[0]) * e[0] + (rr - q[1]) * e[1]
        across = -(cc - CENTRE[0]) * e[1] + (rr - CENTRE[1]) * e[0]
        z[(along > 0) & (np.abs(across) <= 6)] = v
    lev = corner_level(z, [corners[:len(levels)]], [CENTRE], [2 * HALF_DIAG], 0.5)
    assert (lev.weight(0.5) >= 0.5) is below                     # levelled at least half way, or not


def test_level_beyond_the_corners_taken_in_part_near_its_threshold():
    """Two strips at -12 and -35 nm (unseen feedback seed 79) lie under the map's zero by 0.98-1.02 times the
    threshold (2 x their standard error, 24.7 nm): levelled part way (0.43), and a nanometre more or less moves the weight a
    little, not from nothing to everything. Clearly below: in full; under 0.7 times the threshold: not at all."""
    def w(*levels):
        return CornerLevel(levels_nm=np.array(levels, float), strips=np.zeros((2, 2), bool)).weight(0.6)
    assert 0.3 <= w(-12.0, -35.7) <= 0.7
    assert 0.0 < w(-13.0, -35.7) - w(-12.0, -35.7) <= 0.15
    assert w(-30.0, -34.0) == 1.0                       # 32 nm under, the threshold 5.9 nm
    assert w(-2.0, -30.0) == 0.0                        # 16 nm under, the threshold 41.5 nm
    assert w(-30.0) == 0.0                              # one strip
    # the ramp: linear from 0.7 to 1.3 times the threshold
    thr = 2.0 * 1.4826 * 10.0 / np.sqrt(2.0)            # strips 20 nm apart
    for frac, expect in ((0.7, 0.0), (1.0, 0.5), (1.15, 0.75), (1.3, 1.0)):
        mean = -frac * thr
        assert abs(w(mean + 10.0, mean - 10.0) - expect) <= 1e-9, frac


def test_levelled_with_planes_to_the_strips_leaves_the_tails_out():
    """A tilted map (0.2 and -0.1 nm/px) of a conical pit 200 nm deep whose pile-up tails (40 nm, decaying over
    40 px) cover the far field. The level's error at the pit's edge, over the wall's slope (2.9 nm/px), is how
    far the contact boundary moves: levelled as before, more than the corner goal of 1.5 px (measured 2.5 px);
    with planes only and the strips' level taken as zero, within it (1.1 px)."""
    rng = np.random.default_rng(1)
    rr, cc = np.mgrid[0:N, 0:N].astype(float)
    r = np.hypot(cc - CENTRE[0], rr - CENTRE[1])
    depth_nm = 200.0
    truth = np.where(r < HALF_DIAG, -depth_nm * (1 - r / HALF_DIAG), 0.0) + _tails()
    z = truth + 0.2 * cc - 0.1 * rr + 300.0 + rng.normal(0, 0.5, (N, N))
    corners = _corners()
    ring = np.abs(r - HALF_DIAG - 3) <= 2
    slope_nm_px = depth_nm / HALF_DIAG
    plain = level_single(z, 0.1)
    planes = level_single(z, 0.1, fit_bow=False)
    levelled = planes.z_nm - corner_level(planes.z_nm, [corners], [CENTRE], [2 * HALF_DIAG], planes.noise_nm).offset_nm
    moved_plain_px = abs(np.median((plain.z_nm - truth)[ring])) / slope_nm_px
    moved_px = abs(np.median((levelled - truth)[ring])) / slope_nm_px
    assert moved_plain_px > 1.5, moved_plain_px
    assert moved_px <= 1.5, moved_px


# ----------------------------------------------------------------------------- the feedback renderer
def _feedback(tmp_path, seed, **families):
    from markcal.fixtures.indent_afm_feedback import render_feedback, write_feedback
    r = render_feedback(seed, **families)
    gsf, _ = write_feedback(r, str(tmp_path), f"fb{seed}")
    res = run_indents([gsf], None, IndentsOptions())
    tab, t = res.indents, r.truth
    k = int(np.argmin(np.hypot(np.asarray(tab["x_um"]) - t["centre_um"][0], np.asarray(tab["y_um"]) - t["centre_um"][1])))
    tc = np.array(t["corners_um"])
    o = np.radians(tab["orientation_deg"][k])
    e1, e2 = np.array([np.cos(o), np.sin(o)]), np.array([-np.sin(o), np.cos(o)])
    c, h1, h2 = np.array([tab["x_um"][k], tab["y_um"][k]]), tab["diag1_um"][k] / 2, tab["diag2_um"][k] / 2
    mc = np.array([c + h1 * e1, c + h2 * e2, c - h1 * e1, c - h2 * e2])
    corner = min(np.max(np.hypot(*(mc[list(p)] - tc).T)) for p in itertools.permutations(range(4))) / t["pixel_um"]
    return (100 * (tab["d_um"][k] / t["d_um"] - 1), 100 * (tab["depth_nm"][k] / t["depth_nm"] - 1),
            100 * (tab["area_um2"][k] / t["area_um2"] - 1), corner, t, res)


_CLEAN = dict(chipping=False, feedback=False, particles=False, faults=False, scanner=False)


@pytest.mark.parametrize("seed,all_goals", [(31, True), (43, False), (17, False), (10, True), (42, True), (45, True)])
def test_imprint_filling_the_field_measured_from_the_surface_beyond_its_corners(tmp_path, seed, all_goals):
    """Tip only, 83-90 % fill, pile-up 460-1040 nm decaying over 0.1-0.15 d: the far field lay on its tails,
    17-36 nm above the original surface, and every corner ran 2-4 px out (session 20: d +2.52, +2.21,
    +2.41 %; corners 4.2, 3.4, 3.8 px). Levelled with planes to the strips beyond the corners: d and corners
    within the rendered-imprint goals (measured d +0.03, +0.33, +0.14 %; corners 0.7, 0.7, 0.5 px). Seed 31
    meets the depth and area goals too; seeds 43 and 17 do not (43: depth +3.4 %, area +7.3 %: the far
    field's line offsets, fitted through the tails, stay in the rows through the imprint). Seeds 10, 42, 45
    (56-89 % fill, d +0.46, +0.58, +0.41 % in session 20) meet all four goals (-0.20, +0.03, -0.11 %)."""
    d, depth, area, corner, t, res = _feedback(tmp_path, seed, **_CLEAN)
    assert abs(d) <= max(0.5, 100 * t["pixel_um"] / t["d_um"]), d
    assert corner <= 1.5, corner
    if all_goals:
        assert abs(depth) <= 1.0 and abs(area) <= 1.0, (depth, area)
    assert res.files[0].info["levelled_to_corners"] is True
    assert res.files[0].info["corner_level_nm"] < -3.0
