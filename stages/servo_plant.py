"""The reduced second-order macro-stage model (paper 003 sec. 2-3), discretised.

Paper 003 (Zhou, Gao & Zhang, *Actuators* 2024, 13, 433) reduces the fourth-order
macro-micro model (eq. 7) to a second-order one (eq. 12)::

    Gn(s) = x1(s) / uA(s) = 4 kf / (3 m1 s^2 + 3 (c1 + c2 + mu) s + 3 (k1 + k2))

and identifies it from a 1-500 Hz sweep (eq. 13). The text of eq. 13 is garbled in
the source ("G n ( s ) = 4683.3 s 2 + 18.85 s 2 + 61.68"). markcal reconstructs it
in the form of eq. 12 divided by 3 m1, i.e. a monic second-order denominator::

    Gn(s) = b0 / (s^2 + a1 s + a0),   b0 = 4683.3, a1 = 18.85 s^-1, a0 = 61.68 s^-2

(the numerator 4683.3 = 4 kf / 3 m1, the s term 18.85 = (c1 + c2 + mu) / m1, the
constant 61.68 = (k1 + k2) / m1; the stray "2" after "18.85 s" is read as a
typesetting artefact, since eq. 12 has a first-order damping term). The poles are
then real, at -4.21 and -14.64 rad/s. All three coefficients are parameters
(:class:`PlantParams`). Units: input uA in V, output x1 in mm (so b0 is in
mm V^-1 s^-2); this fixes the meaning of the paper's gains, which markcal uses with
errors in mm.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

from markcal.stages.errors import MarkcalError

__all__ = ["PlantParams", "DiscretePlant", "discretise", "plant_frequency_response"]


@dataclass(frozen=True)
class PlantParams:
    """Reduced macro-stage model ``Gn(s) = b0 / (s^2 + a1 s + a0)`` (paper eqs. 12-13).

    Attributes
    ----------
    b0 : float
        High-frequency gain, mm V^-1 s^-2 (paper: 4683.3).
    a1 : float
        Damping term, s^-1 (paper: 18.85).
    a0 : float
        Stiffness term, s^-2 (paper: 61.68).
    ts_s : float
        Sampling period of the controller, s (paper: 0.1 ms).
    """

    b0: float = 4683.3
    a1: float = 18.85
    a0: float = 61.68
    ts_s: float = 1e-4

    def check(self) -> None:
        """Raise :class:`MarkcalError` for a non-physical model."""
        if not (np.isfinite(self.b0) and self.b0 > 0):
            raise MarkcalError(f"plant b0 must be positive (got {self.b0})")
        if not (np.isfinite(self.a1) and self.a1 >= 0 and np.isfinite(self.a0) and self.a0 >= 0):
            raise MarkcalError(f"plant a1 and a0 must be non-negative (got a1={self.a1}, a0={self.a0}): "
                               "the open-loop stage would be unstable")
        if not (np.isfinite(self.ts_s) and 0 < self.ts_s <= 0.01):
            raise MarkcalError(f"sampling period ts_s must be in (0, 0.01] s (got {self.ts_s})")


@dataclass(frozen=True)
class DiscretePlant:
    """Zero-order-hold discretisation ``x[k+1] = A x[k] + B u[k]``, ``y = x[0]``.

    State ``x = (position mm, velocity mm/s)``, input V.
    """

    A: np.ndarray
    B: np.ndarray
    params: PlantParams


def discretise(p: PlantParams) -> DiscretePlant:
    """Exact ZOH discretisation of the reduced model at ``p.ts_s``."""
    p.check()
    Ac = np.array([[0.0, 1.0], [-p.a0, -p.a1]])
    Bc = np.array([0.0, p.b0])
    M = np.zeros((3, 3))
    M[:2, :2] = Ac
    M[:2, 2] = Bc
    E = expm(M * p.ts_s)
    return DiscretePlant(A=E[:2, :2].copy(), B=E[:2, 2].copy(), params=p)


def plant_frequency_response(dp: DiscretePlant, z: np.ndarray) -> np.ndarray:
    """Discrete plant ``Gn(z) = C (zI - A)^-1 B`` at the complex points ``z`` (mm/V)."""
    A, B = dp.A, dp.B
    det = (z - A[0, 0]) * (z - A[1, 1]) - A[0, 1] * A[1, 0]
    # first row of adj(zI - A) times B
    return ((z - A[1, 1]) * B[0] + A[0, 1] * B[1]) / det
