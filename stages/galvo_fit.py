"""Galvo correction models fitted to a sparse grid of commanded vs measured positions.

The physical model follows paper 004 sec. 2.3: the controller turns a commanded
position into mirror angles with its nominal geometry (eqs. 3-4, ``d0``, ``e0``);
the real scanner has its own distances d and e, mirror gains and zero offsets,
axis coupling, and a low-order lens term, and lands by eqs. 1-2. Its 13
parameters are fitted by nonlinear least squares (Levenberg-Marquardt, with a
very weak prior that only pins directions the data cannot see). A smoothing
thin-plate spline, smoothing chosen by leave-one-out CV, takes up what is left.

Models (``KINDS``): ``physical+rbf``, ``rbf`` (a thin-plate spline alone),
``poly3`` (a cubic polynomial). Every model maps a command (mm, controller
frame) to a landing position (mm, measured frame registered to the controller
frame); the correction for a wanted position is the command that lands there.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import galvo
from .errors import MarkcalError
from .limits import check_values
from .grid_smooth import Poly3, ThinPlate, fit_poly3, fit_thin_plate, frame_of

#: evaluation cap of the physical model's Levenberg-Marquardt fit (it converges in well under 100)
MAX_NFEV = 2000

KINDS = ("physical+rbf", "rbf", "poly3")
PARAM_NAMES = ("dd_mm", "de_mm", "gain_x_err", "gain_y_err", "zero_x_rad", "zero_y_rad", "coupling_xy",
               "coupling_yx", "lens_k3_mm", "lens_p1_mm", "lens_p2_mm", "tilt_x", "tilt_y")


@dataclass(frozen=True)
class PhysicalGalvo:
    """The fitted scanner. ``params`` follow ``PARAM_NAMES``; lens terms in mm at ``radius_mm``.

    d = d0 + dd, e = e0 + de; optical angles theta_x = 2 ((1 + gain_x_err) alpha_x
    + zero_x + coupling_xy alpha_y), theta_y likewise; lens: with u = x / radius,
    dx = k3 r_u^2 u + p1 (r_u^2 + 2 u^2) + 2 p2 u v (and symmetric for y); a plate
    tilted by tan(tilt) about y and x then scales the landing by 1 / (1 - (tilt_x x + tilt_y y) / d).
    """

    d0_mm: float
    e0_mm: float
    radius_mm: float
    params: np.ndarray

    def land(self, cmd_mm: np.ndarray) -> np.ndarray:
        """Landing positions (n, 2) mm of commands (n, 2) mm."""
        return _land(np.atleast_2d(np.asarray(cmd_mm, float)), self.params, self.d0_mm, self.e0_mm, self.radius_mm)

    def to_dict(self) -> dict:
        return {"d0_mm": self.d0_mm, "e0_mm": self.e0_mm, "radius_mm": self.radius_mm,
                **{k: float(v) for k, v in zip(PARAM_NAMES, self.params)}}

    @classmethod
    def from_dict(cls, d: dict) -> "PhysicalGalvo":
        return cls(float(d["d0_mm"]), float(d["e0_mm"]), float(d["radius_mm"]),
                   np.array([float(d[k]) for k in PARAM_NAMES]))


def nominal_geometry(lens_mm: float) -> tuple:
    """A typical controller geometry (d, e in mm) for a lens field of ``lens_mm``.

    d is about an f-theta lens's focal length (1.45 x the field), e a 10-25 mm
    mirror spacing; used when the user does not give the controller's values.
    """
    return 1.45 * lens_mm, 10.0 + 0.04 * lens_mm


def _land(cmd, p, d0, e0, radius):
    dd, de, gx, gy, zx, zy, cxy, cyx, k3, p1, p2, sx, sy = p
    ax, ay, _ = galvo.inverse(cmd[:, 0], cmd[:, 1], d0, e0)
    tx = 2.0 * ((1.0 + gx) * ax + zx + cxy * ay)
    ty = 2.0 * ((1.0 + gy) * ay + zy + cyx * ax)
    x, y = galvo.forward(tx, ty, d0 + dd, e0 + de)
    u, v = x / radius, y / radius
    r2 = u * u + v * v
    out = np.column_stack([x + k3 * r2 * u + p1 * (r2 + 2 * u * u) + 2 * p2 * u * v,
                           y + k3 * r2 * v + p2 * (r2 + 2 * v * v) + 2 * p1 * u * v])
    return out / (1.0 - (sx * out[:, :1] + sy * out[:, 1:]) / (d0 + dd))


def _prior_sigma(d0, e0, radius):
    return np.array([0.05 * d0, 0.3 * e0 + 5.0, 0.05, 0.05, 0.01, 0.01, 0.01, 0.01,
                     0.05 * radius, 0.05 * radius, 0.05 * radius, 0.05, 0.05])


def fit_physical(cmd_mm: np.ndarray, land_mm: np.ndarray, d0_mm: float, e0_mm: float,
                 start: np.ndarray | None = None) -> PhysicalGalvo:
    """Fit the physical galvo model by nonlinear least squares.

    Parameters
    ----------
    cmd_mm : ndarray, shape (n, 2)
        Commanded positions, controller frame (mm).
    land_mm : ndarray, shape (n, 2)
        Measured landing positions registered to the controller frame (mm).
    d0_mm, e0_mm : float
        The controller's nominal geometry (mm).
    start : ndarray, optional
        Starting parameters (default: the nominal machine).
    """
    from scipy.optimize import least_squares      # here: the CLI imports this module to list the models
    cmd = np.asarray(cmd_mm, float)
    land = np.asarray(land_mm, float)
    check_values(cmd, "cmd_mm", limit=np.inf)     # non-finite input refused before the solver sees it
    check_values(land, "land_mm", limit=np.inf)
    radius = float(max(np.max(np.abs(cmd)), 1.0))
    sig = _prior_sigma(d0_mm, e0_mm, radius)
    # a parameter one prior sigma away costs as much as a 10 µm residual: pins only what the data cannot see
    w_prior = 1e-2

    def resid(p):
        return np.r_[(_land(cmd, p, d0_mm, e0_mm, radius) - land).ravel(), w_prior * p / sig]

    p0 = np.zeros(len(PARAM_NAMES)) if start is None else np.asarray(start, float)
    sol = least_squares(resid, p0, method="lm", x_scale=sig, xtol=1e-12, ftol=1e-12, max_nfev=MAX_NFEV)
    return PhysicalGalvo(float(d0_mm), float(e0_mm), radius, sol.x)


@dataclass(frozen=True)
class GridModel:
    """A fitted forward model: command (mm, controller frame) -> landing (mm, registered frame).

    landing = base(command) + smooth(command), where base is the physical galvo
    (``physical``) or the identity, and smooth a thin-plate spline or a cubic.
    """

    kind: str
    physical: PhysicalGalvo | None
    smooth: object | None

    def land(self, cmd_mm: np.ndarray) -> np.ndarray:
        c = np.atleast_2d(np.asarray(cmd_mm, float))
        out = self.physical.land(c) if self.physical is not None else c.copy()
        if self.smooth is not None:
            out = out + self.smooth(c)
        return out

    def command(self, wanted_mm: np.ndarray, tol_mm: float = 1e-9, max_iter: int = 50) -> np.ndarray:
        """Commands (n, 2) mm that land on the wanted positions (n, 2) mm.

        Chord-Newton: the step is the miss times the inverse Jacobian of the
        physical part at the wanted position (finite differences; the identity
        without one), so each iteration costs one evaluation of the model.
        """
        w = np.atleast_2d(np.asarray(wanted_mm, float))
        c = w.copy()
        jinv = None
        if self.physical is not None:
            h_mm = 1e-3
            f0 = self.physical.land(w)
            jac = np.stack([(self.physical.land(w + [h_mm, 0.0]) - f0) / h_mm,
                            (self.physical.land(w + [0.0, h_mm]) - f0) / h_mm], axis=2)   # d land_i / d cmd_j
            jinv = np.linalg.inv(jac)
        todo = np.arange(len(w))
        for _ in range(max_iter):
            miss = w[todo] - self.land(c[todo])
            step = miss if jinv is None else np.einsum("nij,nj->ni", jinv[todo], miss)
            c[todo] += step
            todo = todo[np.max(np.abs(step), axis=1) >= tol_mm]
            if not len(todo):
                break
        return c

    def __call__(self, wanted_mm: np.ndarray) -> np.ndarray:
        """Command offsets (n, 2) mm for wanted positions: command = wanted + offset."""
        w = np.atleast_2d(np.asarray(wanted_mm, float))
        return self.command(w) - w

    def to_dict(self) -> dict:
        return {"format": "markcal-grid-model-1", "kind": self.kind,
                "physical": None if self.physical is None else self.physical.to_dict(),
                "smooth": None if self.smooth is None else self.smooth.to_dict()}

    @classmethod
    def from_dict(cls, d: dict) -> "GridModel":
        try:
            kind = d["kind"]
            phys = None if d.get("physical") is None else PhysicalGalvo.from_dict(d["physical"])
            s = d.get("smooth")
            smooth = None if s is None else (Poly3.from_dict(s) if kind == "poly3" else ThinPlate.from_dict(s))
        except (KeyError, TypeError, ValueError) as exc:
            raise MarkcalError(f"not a markcal grid model: {exc}") from None
        if kind not in KINDS:
            raise MarkcalError(f"not a markcal grid model: unknown kind {kind!r}")
        return cls(kind, phys, smooth)


def fit_model(kind: str, cmd_mm: np.ndarray, land_mm: np.ndarray, d0_mm: float, e0_mm: float,
              start: np.ndarray | None = None) -> GridModel:
    """Fit one model kind to commands (n, 2) and registered landings (n, 2), mm."""
    cmd = np.asarray(cmd_mm, float)
    land = np.asarray(land_mm, float)
    if kind == "physical+rbf":
        phys = fit_physical(cmd, land, d0_mm, e0_mm, start)
        tps, _ = fit_thin_plate(cmd, land - phys.land(cmd))
        return GridModel(kind, phys, tps)
    if kind == "rbf":
        return GridModel(kind, None, fit_thin_plate(cmd, land - cmd)[0])
    if kind == "poly3":
        return GridModel(kind, None, fit_poly3(cmd, land - cmd))
    raise MarkcalError(f"unknown model {kind!r} (known: {', '.join(KINDS)}, auto)")


def fold_labels(n: int, folds: int, seed: int) -> np.ndarray:
    """Fold of each of ``n`` points, balanced, from a seeded permutation."""
    return np.random.default_rng(seed).permutation(n) % folds


def cross_validate(kind: str, cmd_mm: np.ndarray, land_mm: np.ndarray, d0_mm: float, e0_mm: float,
                   fold_of: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
    """k-fold prediction errors: each point predicted by the model fitted without its fold.

    Every choice inside the model (physical parameters, the spline's smoothing)
    is made again on each fold's training points.

    Returns
    -------
    ndarray, shape (n, 2)
        Predicted minus measured landing (mm) of each point.
    """
    cmd = np.asarray(cmd_mm, float)
    land = np.asarray(land_mm, float)
    err = np.empty_like(land)
    for f in np.unique(fold_of):
        tr, va = fold_of != f, fold_of == f
        m = fit_model(kind, cmd[tr], land[tr], d0_mm, e0_mm, start)
        err[va] = m.land(cmd[va]) - land[va]
    return err


def rms_mm(err_mm: np.ndarray) -> float:
    """RMS of the Euclidean length of error vectors (n, 2)."""
    e = np.asarray(err_mm, float)
    return float(np.sqrt(np.mean((e * e).sum(axis=1))))


@dataclass(frozen=True)
class ModelChoice:
    """Every model's k-fold CV error and the chosen fitted model."""

    model: GridModel
    cv_rmse_mm: dict          # kind -> RMS Euclidean k-fold prediction error (mm)
    cv_errors_mm: dict        # kind -> (n, 2) prediction errors
    folds: int


def choose_model(kind: str, cmd_mm: np.ndarray, land_mm: np.ndarray, d0_mm: float, e0_mm: float,
                 folds: int = 5, seed: int = 0) -> ModelChoice:
    """Cross-validate every model kind on the same folds and fit the chosen one on all points.

    ``kind`` is one of ``KINDS`` or ``auto`` (the lowest k-fold CV error).
    """
    if kind != "auto" and kind not in KINDS:
        raise MarkcalError(f"unknown model {kind!r} (known: {', '.join(KINDS)}, auto)")
    cmd = np.asarray(cmd_mm, float)
    land = np.asarray(land_mm, float)
    fold_of = fold_labels(len(cmd), folds, seed)
    start = fit_physical(cmd, land, d0_mm, e0_mm).params
    errs = {k: cross_validate(k, cmd, land, d0_mm, e0_mm, fold_of, start) for k in KINDS}
    cv = {k: rms_mm(e) for k, e in errs.items()}
    chosen = min(cv, key=cv.get) if kind == "auto" else kind
    return ModelChoice(fit_model(chosen, cmd, land, d0_mm, e0_mm, start), cv, errs, folds)


def hull_distance_mm(points_mm: np.ndarray, hull_of_mm: np.ndarray) -> np.ndarray:
    """How far (mm) each point lies outside the convex hull of ``hull_of_mm`` (0 inside).

    The largest signed distance to the hull's edge lines: exact beside an edge,
    a lower bound beyond a corner.
    """
    from scipy.spatial import ConvexHull
    h = ConvexHull(np.asarray(hull_of_mm, float))
    eq = h.equations                       # n . x + b <= 0 inside, unit normals
    d = np.asarray(points_mm, float) @ eq[:, :2].T + eq[:, 2]
    return np.maximum(d.max(axis=1), 0.0)


__all__ = ["KINDS", "nominal_geometry", "PARAM_NAMES", "PhysicalGalvo", "fit_physical", "GridModel", "fit_model", "fold_labels",
           "cross_validate", "rms_mm", "ModelChoice", "choose_model", "hull_distance_mm", "frame_of"]
