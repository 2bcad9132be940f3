"""Which way round the plate lies: the grid's symmetric orientations and the choice among them.

A square grid of identical marks looks the same turned by 90, 180 or 270 deg
(and, seen from the back, mirrored), so detection alone cannot say which mark
is row 0 column 0. Three kinds of evidence can:

- an **orientation mark** the plate spec declares: a grid site left unmarked
  (only the orientations in which that site is empty are consistent);
- a **rotation hint** from the user: the plate's in-plane angle in the
  measurement frame to within +-45 deg (the candidates are 90 deg apart);
- the **physical galvo model** (paper 004 eqs. 1-5): the orientation in which
  the model explains the deviations best, when it wins by a wide margin.

A two-mirror galvo's field is even in x and in y, so the model fits a turn by
180 deg and the mirrors about the grid axes exactly as well (its zero offsets,
decentring and tilt terms change sign): its margin is reported, but it cannot
decide alone, and without a mark or a hint ``choose`` refuses.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import MarkcalError
from .galvo_fit import fit_physical, rms_mm
from .register import Lattice, Rigid2D, place_block, rigid_fit

#: the physical model must explain the field this many times better than in any other orientation
MIN_MARGIN = 2.0
#: a hint must lie within this many degrees of a candidate (the candidates are 90 deg apart, so a
#: plate within +-44 deg of the hint is taken; at 44-46 deg it could be either and is refused)
HINT_WINDOW_DEG = 44.0


@dataclass(frozen=True)
class Candidate:
    """One symmetric orientation of the detected grid.

    ``turn`` quarter turns and ``mirrored`` (a flip of the lattice's second
    axis first) map lattice steps to (col, row); ``row``/``col``/``ids`` per detected
    centre (-1: off the grid); ``transform`` the rigid (or mirrored) fit of the
    detected centres (plate frame) onto the nominal grid; ``rotation_deg`` the
    plate's in-plane angle in the measurement frame; ``phys_rms_mm`` the
    physical galvo model's residual RMS over the fiducials.
    """

    turn: int
    mirrored: bool
    row: np.ndarray
    col: np.ndarray
    ids: np.ndarray
    transform: Rigid2D
    rotation_deg: float
    n_placed: int
    phys_rms_mm: float

    @property
    def label(self) -> str:
        return f"{self.rotation_deg:.1f} deg" + (" mirrored" if self.mirrored else "")


@dataclass(frozen=True)
class Choice:
    """The chosen orientation, how it was chosen and how clear the physical model was."""

    chosen: Candidate
    method: str                    # "orientation mark", "rotation hint", "physical model"
    margin: float                  # runner-up / best physical residual RMS (>= 1; inf: no runner-up)
    candidates: tuple


def _steps(k: np.ndarray, turn: int, mirrored: bool) -> np.ndarray:
    a, b = k[:, 0].copy(), k[:, 1].copy()
    if mirrored:
        b = -b
    for _ in range(turn % 4):
        a, b = -b, a
    return np.column_stack([a, b])


def candidates(uv_mm: np.ndarray, lattice: Lattice, nominal_xy_mm: np.ndarray, rows: int, cols: int,
               d_mm: float, e_mm: float, mirror: bool, min_placed_fraction: float = 0.9) -> list:
    """Every symmetric orientation of the detected grid that fits the plate's rows and columns.

    Parameters
    ----------
    uv_mm : ndarray, shape (n, 2)
        Detected centres, plate (measurement) frame.
    lattice : Lattice
        Their lattice coordinates (``register.lattice_coords``).
    nominal_xy_mm : ndarray, shape (rows * cols, 2)
        Nominal centres, GLS frame, id = row * cols + col.
    d_mm, e_mm : float
        The controller's galvo geometry (for the physical model).
    mirror : bool
        Also try the mirrored orientations (a plate measured from the back).
    """
    uv = np.asarray(uv_mm, float)
    out = []
    for mirrored in ((False, True) if mirror else (False,)):
        for turn in range(4):
            st = _steps(lattice.k, turn, mirrored)
            col = place_block(st[:, 0], lattice.good, cols)
            row = place_block(st[:, 1], lattice.good, rows)
            on = (col >= 0) & (row >= 0)
            col, row = np.where(on, col, -1), np.where(on, row, -1)
            out.append((turn, mirrored, row, col, int(on.sum())))
    best = max(c[4] for c in out)
    result = []
    for turn, mirrored, row, col, n_on in out:
        if n_on < max(min_placed_fraction * best, 4):
            continue            # a rectangular plate does not fit this way round
        on = row >= 0
        q = nominal_xy_mm[row[on] * cols + col[on]]
        tf = rigid_fit(uv[on], q, allow_reflection=mirrored)
        if tf.reflection != mirrored:
            continue
        p = tf.apply(uv[on])
        phys = fit_physical(q, p, d_mm, e_mm)
        rot = np.degrees(np.arctan2(tf.rotation[0, 1], tf.rotation[0, 0]))
        result.append(Candidate(turn, mirrored, row, col, np.where(on, row * cols + col, -1), tf, float(rot), n_on, rms_mm(phys.land(q) - p)))
    return result


def _angle_diff_deg(a: float, b: float) -> float:
    return float(abs((a - b + 180.0) % 360.0 - 180.0))


def choose(cands: list, mark_id: int | None = None, hint_deg: float | None = None,
           min_margin: float = MIN_MARGIN) -> Choice:
    """Choose the orientation by the orientation mark, else the hint, else the physical model.

    Parameters
    ----------
    cands : list of Candidate
    mark_id : int, optional
        Id (row * cols + col) of the site the plate leaves unmarked.
    hint_deg : float, optional
        The plate's approximate in-plane angle in the measurement frame (deg).

    Raises
    ------
    MarkcalError
        When the evidence does not single out one orientation; the message
        says what was seen and how to resolve it.
    """
    if not cands:
        raise MarkcalError("the detected marks fit the plate's rows and columns in no orientation")
    pool = list(cands)
    method = "physical model"
    if mark_id is not None:
        pool = [c for c in pool if not np.any(c.ids == mark_id)]
        method = "orientation mark"
        if not pool:
            tried = "" if any(c.mirrored for c in cands) else " (mirrored orientations not tried: --mirror auto)"
            raise MarkcalError("the orientation mark (an unmarked grid site) was not found: that site holds "
                               f"a mark in every orientation{tried}; check [fiducial] orientation_mark")
    if hint_deg is not None:
        near = [c for c in pool if _angle_diff_deg(c.rotation_deg, hint_deg) <= HINT_WINDOW_DEG]
        if not near:
            got = ", ".join(sorted({c.label for c in pool}))
            raise MarkcalError(f"no orientation within {HINT_WINDOW_DEG:.0f} deg of --rotation-hint-deg "
                               f"{hint_deg:g}: the grid lies at {got}; give the plate's angle to within "
                               f"{HINT_WINDOW_DEG:.0f} deg")
        pool = near
        if method == "physical model":
            method = "rotation hint"
    ranked = sorted(pool, key=lambda c: c.phys_rms_mm)
    others = sorted(cands, key=lambda c: c.phys_rms_mm)
    best = ranked[0]
    runner = [c for c in others if c is not best]
    margin = runner[0].phys_rms_mm / max(best.phys_rms_mm, 1e-12) if runner else float("inf")
    if len(ranked) > 1:
        second = ranked[1]
        m_pool = second.phys_rms_mm / max(best.phys_rms_mm, 1e-12)
        if m_pool < min_margin:
            raise MarkcalError(f"the plate's orientation is ambiguous: {_why_open(ranked, mark_id, hint_deg)}; "
                               f"the galvo model fits {best.label} ({best.phys_rms_mm * 1000:.1f} um RMS) and "
                               f"{second.label} ({second.phys_rms_mm * 1000:.1f} um RMS) nearly equally "
                               f"(margin {m_pool:.2f}, needs {min_margin:g}; a galvo field looks alike turned by "
                               f"180 deg); give --rotation-hint-deg ANGLE (the plate's angle in the scan, within "
                               f"{HINT_WINDOW_DEG:.0f} deg; 0: laid upright) or declare [fiducial] "
                               "orientation_mark = [row, col] (a site left unmarked) in the plate spec")
        method = "physical model" if method == "physical model" else method + " + physical model"
    return Choice(chosen=best, method=method, margin=float(margin), candidates=tuple(cands))


def _why_open(pool: list, mark_id, hint_deg) -> str:
    """Why more than one orientation is still open (for the refusal message)."""
    if mark_id is None and hint_deg is None:
        return "the plate spec declares no orientation mark and no --rotation-hint-deg was given"
    if len({c.mirrored for c in pool}) == 2:
        return f"{len(pool)} orientations (mirrored and not) are consistent with the evidence (give --mirror yes or no)"
    if mark_id is not None:
        return (f"the orientation mark's site is empty in {len(pool)} orientations "
                "(another mark is missing where the mark would be if the plate were turned)")
    return f"{len(pool)} orientations lie within {HINT_WINDOW_DEG:.0f} deg of the hint"
