"""XY(θz) stage self-calibration from an artifact plate measured in four views (paper 001).

Model (paper 001 §2-3; the text's equations are garbled, this is the
reconstruction, stated in full so that it can be checked):

* Sites (m, n), m, n = -M..M, M = (N - 1)/2, at (x, y) = (m, n)·Δ on the
  stage. The stage reads a point at true position p as p + G(p): G is the
  stage error, sampled at the sites (µm).
* Plate mark (m, n) sits at (m, n)·Δ + A(m, n) in the plate frame (A, the
  artifact error, µm). Angular mark k lies at θ_k = k·360/K + Aθ(k).
* A view v puts the plate at a pose: rotation R_v (0, +90° or +360/K about the
  origin), shift s_v (one pitch along +X in view 3), then a misalignment
  rotation φ_v about the plate origin and offset t_v. So mark (m, n) truly
  lies at ``R(φ_v) R_v (p + A) + s_v + t_v`` and its measured deviation from
  the nominal position of the site it sits on is::

      V = G(site) + R(φ_v) R_v A + (R(φ_v) - I) R_v p + t_v      (µm; p in µm)

  The rotation is kept exact (a 0.3° misalignment has a 0.7 µm second-order
  term over a 100 mm plate); the fit is Gauss-Newton in φ.
* Angular mark k in view v sits on stage line l_v(k) = k, k + K/4, k + 1, k
  (views 0, 1, 2, 3) and reads ``Vθ = Gθ(l) + Aθ(k) + φ_v``.
* Gauge (what self-calibration cannot see, fixed by definition, paper eqs. 5
  and 11): G has no translation, no rotation, no magnification; A has no
  translation and no rotation. O and R are the two remaining linear terms of G:
  ``Gx = R·x + O·y + Fx``, ``Gy = O·x - R·y + Fy``.
* Paper eq. 9 (the "new property"): Gθ on the ±X and ±Y axes equals the mean
  angle deviation of the sites on that half axis, (x·Gy - y·Gx)/(x² + y²).
  As in paper eq. 27 these four relations enter as least-squares equations,
  weighted like angle measurements; they fix the level of Gθ, which the angle
  views alone leave free.

Everything is solved at once: one sparse equality-constrained least-squares
problem over G, A, Gθ, Aθ and every view's misalignment (unknowns in µm and
mrad; 1 µm/mm = 1 mrad), each equation weighted by its group's noise level,
which is estimated from the residuals. The same factorisation gives the
covariance of the estimate: the bound the solution reaches on this data.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import scipy.linalg.lapack
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from markcal.stages.errors import MarkcalError

__all__ = ["SelfcalSetup", "GridViews", "AngleViews", "SelfcalSolution", "GRID_VIEWS", "ANGLE_VIEWS",
           "site_xy_mm", "view_site", "view_line", "tie_rows", "linear_terms", "solve_selfcal"]

#: views in which the grid marks are measured, and those in which the angular marks are
GRID_VIEWS = (0, 1, 3)
ANGLE_VIEWS = (0, 1, 2, 3)
_RAD_PER_DEG = np.pi / 180.0


@dataclass(frozen=True)
class SelfcalSetup:
    """An artifact plate and the views measured.

    Attributes
    ----------
    n : int
        Sites per side (odd).
    pitch_mm : float
        Site interval Δ.
    k : int
        Angular lines (a multiple of 4); 0 for an XY-only calibration.
    views : tuple of int
        Views measured (subset of 0, 1, 2, 3).
    """

    n: int = 11
    pitch_mm: float = 10.0
    k: int = 24
    views: tuple = (0, 1, 2, 3)

    def __post_init__(self):
        if self.n < 3 or self.n % 2 == 0:
            raise MarkcalError(f"n must be odd and at least 3 (got {self.n}): the plate origin is the centre mark")
        if not self.pitch_mm > 0:
            raise MarkcalError("pitch_mm must be positive")
        if self.k < 0 or self.k % 4:
            raise MarkcalError(f"k must be a multiple of 4 (got {self.k}): view 1 turns the plate by K/4 lines")
        if any(v not in (0, 1, 2, 3) for v in self.views) or len(set(self.views)) != len(self.views):
            raise MarkcalError(f"views must be distinct values of 0, 1, 2, 3 (got {list(self.views)})")

    @property
    def half(self) -> int:
        return (self.n - 1) // 2


@dataclass(frozen=True)
class GridViews:
    """Measured grid-mark deviations, one row per mark and view (stage frame, µm)."""

    view: np.ndarray
    m: np.ndarray
    n: np.ndarray
    vx_um: np.ndarray
    vy_um: np.ndarray


@dataclass(frozen=True)
class AngleViews:
    """Measured angle deviations, one row per angular mark and view (deg)."""

    view: np.ndarray
    k: np.ndarray
    vtheta_deg: np.ndarray


@dataclass(frozen=True)
class SelfcalSolution:
    """The stage error map and everything estimated with it.

    Arrays over sites are (N, N) indexed ``[m + M, n + M]`` (m along x).
    """

    gx_um: np.ndarray
    gy_um: np.ndarray
    ax_um: np.ndarray
    ay_um: np.ndarray
    gtheta_deg: np.ndarray
    atheta_deg: np.ndarray
    nonorthogonality_urad: float
    scale_difference_ppm: float
    fx_um: np.ndarray
    fy_um: np.ndarray
    misalignment: dict
    residual_rms_xy_um: float
    residual_rms_theta_deg: float
    sigma_xy_um: float
    sigma_theta_deg: float
    predicted_sd_gx_um: np.ndarray
    predicted_sd_gy_um: np.ndarray
    predicted_sd_gtheta_deg: np.ndarray
    condition_1norm: float
    iterations: int
    n_grid_rows: int
    n_angle_rows: int
    notes: tuple = field(default_factory=tuple)


def site_xy_mm(setup: SelfcalSetup, m, n) -> tuple:
    """Nominal stage position (x, y) in mm of site (m, n)."""
    return np.asarray(m, float) * setup.pitch_mm, np.asarray(n, float) * setup.pitch_mm


def view_site(view: int, m, n) -> tuple:
    """The site (m', n') on which plate mark (m, n) sits in ``view``."""
    m, n = np.asarray(m), np.asarray(n)
    if view == 1:
        return -n, m
    if view == 3:
        return m + 1, n
    if view == 0:
        return m, n
    raise ValueError(f"grid marks are not measured in view {view}")


def view_line(view: int, k, n_lines: int):
    """The stage angular line on which angular mark ``k`` lies in ``view``."""
    shift = {0: 0, 1: n_lines // 4, 2: 1, 3: 0}[view]
    return (np.asarray(k) + shift) % n_lines


def _view_rotation(view: int) -> np.ndarray:
    return np.array([[0.0, -1.0], [1.0, 0.0]]) if view == 1 else np.eye(2)


def _rot(phi: float) -> np.ndarray:
    c, s = np.cos(phi), np.sin(phi)
    return np.array([[c, -s], [s, c]])


def tie_rows(setup: SelfcalSetup) -> list:
    """Paper eq. 9: for lines 0, K/4, K/2, 3K/4 the (site index, component, weight) lists.

    Gθ(line) [mrad] = Σ weight · G_component(site) [µm] (the mean angle
    deviation, (x·Gy - y·Gx)/(x² + y²), of the sites on that half axis).
    """
    M, N, K = setup.half, setup.n, setup.k
    rows = []
    for q, (dm, dn) in enumerate(((1, 0), (0, 1), (-1, 0), (0, -1))):
        terms = []
        for j in range(1, M + 1):
            m, n = dm * j, dn * j
            x, y = m * setup.pitch_mm, n * setup.pitch_mm
            r2 = x * x + y * y
            idx = (m + M) * N + (n + M)
            if x:
                terms.append((idx, 1, x / r2 / M))   # + x·Gy / r²
            else:
                terms.append((idx, 0, -y / r2 / M))  # - y·Gx / r²
        rows.append((q * K // 4, terms))
    return rows


def linear_terms(setup: SelfcalSetup, gx_um: np.ndarray, gy_um: np.ndarray) -> tuple:
    """Split a stage map into non-orthogonality O, scale difference R and residual F.

    ``Gx = R·x + O·y + Fx``, ``Gy = O·x - R·y + Fy`` (least squares over the
    sites). Returns ``(O_urad, R_ppm, Fx_um, Fy_um)``.
    """
    M = setup.half
    m, n = np.meshgrid(np.arange(-M, M + 1), np.arange(-M, M + 1), indexing="ij")
    x, y = site_xy_mm(setup, m, n)
    # basis fields (µm per 1e-6 of the coefficient, with x, y in mm -> x*1e3 µm)
    ox, oy = y * 1e-3, x * 1e-3
    rx, ry = x * 1e-3, -y * 1e-3
    a = np.column_stack([np.r_[ox.ravel(), oy.ravel()], np.r_[rx.ravel(), ry.ravel()]])
    g = np.r_[gx_um.ravel(), gy_um.ravel()]
    (o_u, r_u), *_ = np.linalg.lstsq(a, g, rcond=None)
    fx = gx_um - o_u * ox - r_u * rx
    fy = gy_um - o_u * oy - r_u * ry
    return float(o_u), float(r_u), fx, fy


class _Layout:
    """Unknown vector layout: G (2S), A (2S), per view φ (and t for grid views), Gθ (K), Aθ (K)."""

    def __init__(self, n_sites: int, n_lines: int, grid_views, angle_views):
        self.S = n_sites
        self.K = n_lines
        nxt = 4 * self.S
        self.phi, self.t = {}, {}
        for v in sorted(set(grid_views) | set(angle_views)):
            self.phi[v] = nxt
            nxt += 1
        for v in sorted(grid_views):
            self.t[v] = nxt
            nxt += 2
        self.gth = nxt
        self.ath = nxt + self.K
        self.size = nxt + 2 * self.K

    def g(self, site):
        return 2 * np.asarray(site)

    def a(self, mark):
        return 2 * self.S + 2 * np.asarray(mark)


def _check_inputs(setup: SelfcalSetup, grid: GridViews, angle: AngleViews | None) -> list:
    notes = []
    M, N = setup.half, setup.n
    gv = sorted(set(np.unique(grid.view).tolist()))
    missing = [v for v in GRID_VIEWS if v not in gv]
    if missing:
        raise MarkcalError(f"grid views {missing} missing: the XY solution needs views 0, 1 and 3")
    extra = [v for v in gv if v not in GRID_VIEWS]
    if extra:
        raise MarkcalError(f"grid marks are measured in views 0, 1 and 3 only, not {extra}")
    expected = {0: N * N, 1: N * N, 3: N * (N - 1)}
    for v in GRID_VIEWS:
        got = int(np.sum(grid.view == v))
        if got < expected[v]:
            notes.append(f"grid view {v}: {expected[v] - got} of {expected[v]} marks not measured; "
                         "solved with the others")
    if angle is not None:
        av = sorted(set(np.unique(angle.view).tolist()))
        if 0 not in av or 2 not in av:
            raise MarkcalError(f"angle views {[v for v in (0, 2) if v not in av]} missing: "
                               "the θz solution needs views 0 and 2")
        for v in av:
            got = int(np.sum(angle.view == v))
            if got < setup.k:
                notes.append(f"angle view {v}: {setup.k - got} of {setup.k} marks not measured; "
                             "solved with the others")
    # every site and mark must be seen at least once
    site_seen = np.zeros((N, N), bool)
    mark_seen = np.zeros((N, N), bool)
    for v in GRID_VIEWS:
        sel = grid.view == v
        sm, sn = view_site(v, grid.m[sel], grid.n[sel])
        site_seen[sm + M, sn + M] = True
        mark_seen[grid.m[sel] + M, grid.n[sel] + M] = True
    if not site_seen.all():
        bad = np.argwhere(~site_seen)[0] - M
        raise MarkcalError(f"site (m={bad[0]}, n={bad[1]}) is not measured in any view: "
                           "its stage error cannot be determined")
    if not mark_seen.all():
        bad = np.argwhere(~mark_seen)[0] - M
        raise MarkcalError(f"mark (m={bad[0]}, n={bad[1]}) is not measured in any view")
    return notes


def _gauge(setup: SelfcalSetup, lay: _Layout) -> sp.csr_matrix:
    """The 7 gauge constraints (rows) on G and A."""
    M = setup.half
    m, n = np.meshgrid(np.arange(-M, M + 1), np.arange(-M, M + 1), indexing="ij")
    x, y = (v.ravel() for v in site_xy_mm(setup, m, n))
    s = np.arange(lay.S)
    rows, cols, vals = [], [], []

    def add(r, c, v):
        rows.append(np.full(len(c), r))
        cols.append(c)
        vals.append(v)

    ones = np.ones(lay.S)
    for base, r0, with_mag in ((lay.g(s), 0, True), (lay.a(s), 4, False)):
        add(r0, base, ones)                                  # no translation x
        add(r0 + 1, base + 1, ones)                          # no translation y
        add(r0 + 2, np.r_[base, base + 1], np.r_[-y, x])     # no rotation
        if with_mag:
            add(r0 + 3, np.r_[base, base + 1], np.r_[x, y])  # no magnification
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(7, lay.size))


def _assemble(setup, lay, grid, angle, x_hat, w_xy, w_th):
    """Jacobian rows (weighted) and residuals at the current estimate."""
    M, N = setup.half, setup.n
    rows, cols, vals, res = [], [], [], []
    r0 = 0
    for v in GRID_VIEWS:
        sel = np.flatnonzero(grid.view == v)
        if not len(sel):
            continue
        mk, nk = grid.m[sel], grid.n[sel]
        sm, sn = view_site(v, mk, nk)
        site = (sm + M) * N + (sn + M)
        mark = (mk + M) * N + (nk + M)
        rv = _view_rotation(v)
        phi = x_hat[lay.phi[v]] * 1e-3
        rp = _rot(phi) @ rv                               # R(φ) R_v
        jrp = np.array([[0.0, -1.0], [1.0, 0.0]]) @ rp   # d/dφ of R(φ) R_v
        p_um = np.column_stack([mk, nk]) * setup.pitch_mm * 1e3
        a = np.column_stack([x_hat[lay.a(mark)], x_hat[lay.a(mark) + 1]])
        g = np.column_stack([x_hat[lay.g(site)], x_hat[lay.g(site) + 1]])
        t = x_hat[lay.t[v]:lay.t[v] + 2]
        q = p_um + a
        pred = g + a @ rp.T + p_um @ (rp - rv).T + t
        dphi = (q @ jrp.T) * 1e-3                         # µm per mrad
        meas = np.column_stack([grid.vx_um[sel], grid.vy_um[sel]])
        r = meas - pred
        n_eq = len(sel)
        for c in range(2):                                # equation rows: x then y per mark
            ridx = r0 + 2 * np.arange(n_eq) + c
            rows += [ridx, ridx, ridx, ridx, ridx]
            cols += [lay.g(site) + c, lay.a(mark), lay.a(mark) + 1,
                     np.full(n_eq, lay.phi[v]), np.full(n_eq, lay.t[v] + c)]
            vals += [np.ones(n_eq), np.full(n_eq, rp[c, 0]), np.full(n_eq, rp[c, 1]),
                     dphi[:, c], np.ones(n_eq)]
        res.append(r.ravel())
        r0 += 2 * n_eq
    n_grid = r0
    scale = [np.full(n_grid, w_xy)]
    if angle is not None:
        K = setup.k
        for v in sorted(set(np.unique(angle.view).tolist())):
            sel = np.flatnonzero(angle.view == v)
            k = angle.k[sel]
            line = view_line(v, k, K)
            meas = angle.vtheta_deg[sel] * _RAD_PER_DEG * 1e3
            pred = x_hat[lay.gth + line] + x_hat[lay.ath + k] + x_hat[lay.phi[v]]
            ridx = r0 + np.arange(len(sel))
            rows += [ridx, ridx, ridx]
            cols += [lay.gth + line, lay.ath + k, np.full(len(sel), lay.phi[v])]
            vals += [np.ones(len(sel))] * 3
            res.append(meas - pred)
            r0 += len(sel)
        for line, terms in tie_rows(setup):               # paper eq. 9 as equations
            idx = np.array([lay.g(s) + c for s, c, _ in terms])
            wts = np.array([w for _, _, w in terms])
            rows += [np.full(len(idx) + 1, r0)]
            cols += [np.r_[lay.gth + line, idx]]
            vals += [np.r_[1.0, -wts]]
            res.append(np.array([-(x_hat[lay.gth + line] - wts @ x_hat[idx])]))
            r0 += 1
        scale.append(np.full(r0 - n_grid, w_th))
    w = np.concatenate(scale)
    jac = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                        shape=(r0, lay.size))
    return sp.diags(w) @ jac, w * np.concatenate(res), n_grid, r0 - n_grid


def _kkt(jw, gauge):
    n_c = gauge.shape[0]
    top = sp.hstack([jw.T @ jw, gauge.T])
    bot = sp.hstack([gauge, sp.csr_matrix((n_c, n_c))])
    return sp.vstack([top, bot]).tocsc()


def solve_selfcal(setup: SelfcalSetup, grid: GridViews, angle: AngleViews | None = None,
                  max_iter: int = 10, tol_mrad: float = 1e-12, bound: bool = True) -> SelfcalSolution:
    """Solve the stage error map from the measured views.

    Parameters
    ----------
    setup : SelfcalSetup
        Plate geometry (N, Δ, K).
    grid : GridViews
        Grid-mark deviations of views 0, 1 and 3 (µm, stage frame).
    angle : AngleViews, optional
        Angular-mark deviations of views 0 and 2 (and 1, 3 when measured), deg.
        Without it the calibration is XY only.
    max_iter : int
        Gauss-Newton iterations (the misalignment rotations are the only
        non-linear unknowns; 3-4 iterations converge).
    tol_mrad : float
        Stop when no misalignment rotation changes by more than this.
    bound : bool
        Compute the covariance bound (predicted sd of every G and Gθ value)
        and the condition number; without it those fields are NaN.

    Returns
    -------
    SelfcalSolution
    """
    if angle is not None and setup.k < 4:
        raise MarkcalError(f"k must be a positive multiple of 4 (got {setup.k})")
    notes = _check_inputs(setup, grid, angle)
    av = sorted(set(np.unique(angle.view).tolist())) if angle is not None else []
    lay = _Layout(setup.n * setup.n, setup.k if angle is not None else 0, GRID_VIEWS, av)
    gauge = _gauge(setup, lay)
    x_hat = np.zeros(lay.size)
    w_th = 1.0
    it = 0
    for pass_ in range(2):          # pass 0 with unit weights, pass 1 weighted by the estimated noise
        # chord Gauss-Newton: one factorisation per pass; the Jacobian depends on
        # the misalignment rotations only through R(φ) ≈ I, so it converges fast
        jw, rw, n_grid, n_ang = _assemble(setup, lay, grid, angle, x_hat, 1.0, w_th)
        kkt = _kkt(jw, gauge)
        try:
            lu = spla.splu(kkt, permc_spec="MMD_AT_PLUS_A")
        except RuntimeError:
            raise MarkcalError("the views do not determine the stage error (singular system)") from None
        for _ in range(max_iter):
            it += 1
            step = lu.solve(np.r_[jw.T @ rw, -(gauge @ x_hat)])[:lay.size]
            if not np.all(np.isfinite(step)):
                raise MarkcalError("the views do not determine the stage error (singular system)")
            x_hat = x_hat + step
            if np.max(np.abs(step[list(lay.phi.values())])) < tol_mrad:
                break
            _, rw, _, _ = _assemble(setup, lay, grid, angle, x_hat, 1.0, w_th)
        jw, rw, n_grid, n_ang = _assemble(setup, lay, grid, angle, x_hat, 1.0, w_th)
        r_xy = rw[:n_grid]
        dof_xy = max(n_grid - (4 * lay.S + 3 * len(GRID_VIEWS) - 7), 1)
        sig_xy = float(np.sqrt(np.sum(r_xy ** 2) / dof_xy))
        if angle is not None:
            r_th = rw[n_grid:] / w_th
            dof_th = max(n_ang - (2 * lay.K + len(av)), 1)
            sig_th = float(np.sqrt(np.sum(r_th ** 2) / dof_th))
        else:
            r_th, sig_th = np.zeros(0), 0.0
        if pass_ == 1 or angle is None:
            break
        # weights relative to the grid equations (kept finite for noise-free data)
        if sig_xy > 1e-12 and sig_th > 1e-12:
            w_th = float(np.clip(sig_xy / sig_th, 1e-3, 1e3))
    # covariance bound: (J'WJ)^-1 under the constraints = top-left block of the KKT inverse
    kkt = _kkt(jw, gauge)
    want = np.r_[np.arange(2 * lay.S), lay.gth + np.arange(lay.K)]
    if not bound:
        cov_diag, cond = np.full(len(want), np.nan), float("nan")
    elif kkt.shape[0] <= 6000:        # dense LAPACK: BLAS-3 solves with many right-hand sides
        dense = kkt.toarray()
        lu_d, piv = scipy.linalg.lu_factor(dense, check_finite=False)
        e = np.zeros((kkt.shape[0], len(want)))
        e[want, np.arange(len(want))] = 1.0
        cov_diag = np.einsum("ij,ij->j", scipy.linalg.lu_solve((lu_d, piv), e, check_finite=False), e)
        rcond, _ = scipy.linalg.lapack.dgecon(lu_d, np.abs(dense).sum(axis=0).max(), norm="1")
        cond = float(1.0 / rcond) if rcond > 0 else float("inf")
    else:                           # large plates: sparse solves, one column at a time
        lu = spla.splu(kkt, permc_spec="MMD_AT_PLUS_A")
        cov_diag = np.array([lu.solve(np.eye(1, kkt.shape[0], i).ravel())[i] for i in want])
        inv_norm = spla.onenormest(spla.LinearOperator(kkt.shape, matvec=lu.solve,
                                                       rmatvec=lambda b: lu.solve(b, trans="T")))
        cond = float(spla.norm(kkt, 1) * inv_norm)
    cov_diag = np.where(np.isnan(cov_diag), np.nan, np.maximum(cov_diag, 0.0))

    N = setup.n
    g = x_hat[:2 * lay.S].reshape(lay.S, 2)
    a = x_hat[2 * lay.S:4 * lay.S].reshape(lay.S, 2)
    gx, gy = g[:, 0].reshape(N, N), g[:, 1].reshape(N, N)
    o_u, r_u, fx, fy = linear_terms(setup, gx, gy)
    mrad_to_deg = 1e-3 / _RAD_PER_DEG
    misalign = {}
    for v, i in lay.phi.items():
        misalign[f"view{v}_rotation_deg"] = float(x_hat[i] * mrad_to_deg)
        if v in lay.t:
            misalign[f"view{v}_offset_x_um"] = float(x_hat[lay.t[v]])
            misalign[f"view{v}_offset_y_um"] = float(x_hat[lay.t[v] + 1])
    sd = np.sqrt(cov_diag) * sig_xy      # weights are relative to the grid equations
    return SelfcalSolution(
        gx_um=gx, gy_um=gy, ax_um=a[:, 0].reshape(N, N), ay_um=a[:, 1].reshape(N, N),
        gtheta_deg=x_hat[lay.gth:lay.gth + lay.K] * mrad_to_deg,
        atheta_deg=x_hat[lay.ath:lay.ath + lay.K] * mrad_to_deg,
        nonorthogonality_urad=o_u, scale_difference_ppm=r_u, fx_um=fx, fy_um=fy,
        misalignment=misalign,
        residual_rms_xy_um=float(np.sqrt(np.mean(r_xy ** 2))),
        residual_rms_theta_deg=float(np.sqrt(np.mean(r_th ** 2)) * mrad_to_deg) if len(r_th) else 0.0,
        sigma_xy_um=sig_xy, sigma_theta_deg=sig_th * mrad_to_deg,
        predicted_sd_gx_um=sd[0:2 * lay.S:2].reshape(N, N),
        predicted_sd_gy_um=sd[1:2 * lay.S:2].reshape(N, N),
        predicted_sd_gtheta_deg=sd[2 * lay.S:] * mrad_to_deg,
        condition_1norm=cond, iterations=it, n_grid_rows=n_grid, n_angle_rows=n_ang,
        notes=tuple(notes))
