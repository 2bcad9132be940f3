"""Kinematic model of the precision-marking (PM) machine (paper 000, eqs. 1-8).

All lengths in µm. Frames: ``_cmd`` is the commanded stage position, ``_pm``
the tool-tip position in the PM (reference-instrument) frame, ``_om`` the
optical-microscope frame in which the workpiece and the targets are seen.

The model::

    p_pm  = A · S · c_cmd + s(c_cmd) + o             (axes, eqs. 1-3)
    X_om  = R · p_pm + T                              (pose, eq. 4)
    z_om  = a · x_om + b · y_om + c                   (workpiece plane, eqs. 5-7)

``A`` holds the three unit axis directions as columns (non-orthogonal);
``A = Q · N(γ)`` with ``Q`` a rotation (the orthonormal triad of the stage in
the PM frame) and ``N`` the unit-column shear built from the three
non-orthogonality angles γ = (γxy, γxz, γyz) (rad): ``n_x = (1, 0, 0)``,
``n_y ∝ (γxy, 1, 0)``, ``n_z ∝ (γxz, γyz, 1)``.  ``S = diag(1 + ε)`` holds the
scale errors.  The straightness ``s_i(c) = Σ_{j≠i} K[i, j]·(c_j / L)²`` is
quadratic in each axis's travel with ``L = STRAIGHTNESS_REF_UM`` so that
``K`` (µm) is the straightness bow at ``c_j = ±L``.

Command generation (eq. 8, made exact): the target ``(x, y)`` on the
workpiece in the OM frame is lifted to the plane, pushed ``D`` along the
inward normal, mapped back to the PM frame with ``Rᵀ(X − T)`` and the
stage model is inverted by Newton's method (no first-order truncation).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["STRAIGHTNESS_REF_UM", "PMModel", "rotvec_to_matrix", "matrix_to_rotvec", "shear_matrix",
           "gram_schmidt", "nonorthogonality_rad", "tip_pm", "tip_om", "surface_target_om", "command_for_targets",
           "model_to_dict", "model_from_dict", "PARAM_KEYS", "landing_errors"]

#: reference travel (µm) at which the straightness coefficients K are quoted
STRAIGHTNESS_REF_UM = 25000.0

#: off-diagonal index pairs (i, j) of K: component i bowing as axis j moves
K_PAIRS = ((1, 0), (2, 0), (0, 1), (2, 1), (0, 2), (1, 2))


def rotvec_to_matrix(r: np.ndarray) -> np.ndarray:
    """Rotation matrices from rotation vectors (rad), shape (..., 3) -> (..., 3, 3) (Rodrigues)."""
    r = np.asarray(r, float)
    th = np.linalg.norm(r, axis=-1)[..., None, None]
    k = np.zeros(r.shape[:-1] + (3, 3))
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -r[..., 2], r[..., 1], -r[..., 0]
    k[..., 1, 0], k[..., 2, 0], k[..., 2, 1] = r[..., 2], -r[..., 1], r[..., 0]
    small = th < 1e-8
    th_s = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th ** 2 / 6, np.sin(th_s) / th_s)
    b = np.where(small, 0.5 - th ** 2 / 24, (1 - np.cos(th_s)) / th_s ** 2)
    return np.eye(3) + a * k + b * (k @ k)


def matrix_to_rotvec(m: np.ndarray) -> np.ndarray:
    """Rotation vector (rad) of a 3 x 3 rotation matrix."""
    m = np.asarray(m, float)
    c = np.clip((np.trace(m) - 1) / 2, -1.0, 1.0)
    th = np.arccos(c)
    v = np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]])
    if th < 1e-8:
        return v / 2
    return v * th / (2 * np.sin(th))


def shear_matrix(g: np.ndarray) -> np.ndarray:
    """Unit-column shear N(γ) for non-orthogonality angles γ = (γxy, γxz, γyz) (rad), (..., 3) -> (..., 3, 3)."""
    g = np.asarray(g, float)
    n = np.zeros(g.shape[:-1] + (3, 3))
    n[..., 0, 0] = 1.0
    ny = np.stack([g[..., 0], np.ones_like(g[..., 0]), np.zeros_like(g[..., 0])], -1)
    nz = np.stack([g[..., 1], g[..., 2], np.ones_like(g[..., 0])], -1)
    n[..., :, 1] = ny / np.linalg.norm(ny, axis=-1, keepdims=True)
    n[..., :, 2] = nz / np.linalg.norm(nz, axis=-1, keepdims=True)
    return n


def gram_schmidt(cos9: np.ndarray) -> np.ndarray:
    """Right-handed orthonormal triads from nine direction cosines (§3.1 projection).

    Parameters
    ----------
    cos9 : ndarray, shape (..., 9)
        The x, y and z axis vectors stacked (x1, x2, x3, y1, y2, y3, z1, z2, z3).

    Returns
    -------
    ndarray, shape (..., 3, 3)
        Columns: x normalised; y orthogonalised against x and normalised; z = x × y
        (the z genes only fix nothing but are kept, as in the paper's chromosome).
    """
    v = np.asarray(cos9, float).reshape(cos9.shape[:-1] + (3, 3))
    x = v[..., 0, :] / np.linalg.norm(v[..., 0, :], axis=-1, keepdims=True)
    y = v[..., 1, :] - np.sum(v[..., 1, :] * x, -1, keepdims=True) * x
    y = y / np.linalg.norm(y, axis=-1, keepdims=True)
    z = np.cross(x, y)
    return np.stack([x, y, z], -1)


def nonorthogonality_rad(a: np.ndarray) -> np.ndarray:
    """Departures from 90° (rad) of the axis pairs (xy, xz, yz) of a triad with columns as axes."""
    a = a / np.linalg.norm(a, axis=-2, keepdims=True)
    d = [np.sum(a[..., :, i] * a[..., :, j], -1) for i, j in ((0, 1), (0, 2), (1, 2))]
    return np.arcsin(np.clip(np.stack(d, -1), -1, 1))


@dataclass(frozen=True)
class PMModel:
    """Parameters of the PM machine (see the module docstring).

    Attributes
    ----------
    a_axes : (3, 3) unit axis directions as columns, PM frame.
    scale : (3,) scale errors ε (dimensionless; ppm = 1e6·ε).
    k_um : (6,) straightness bows at ±L in the order of ``K_PAIRS``, µm.
    o_um : (3,) offset, PM frame, µm.
    r_pose : (3, 3) rotation PM -> OM.
    t_um : (3,) translation PM -> OM, µm.
    plane : (3,) workpiece plane a, b (dimensionless), c (µm) in the OM frame.
    """
    a_axes: np.ndarray
    scale: np.ndarray
    k_um: np.ndarray
    o_um: np.ndarray
    r_pose: np.ndarray
    t_um: np.ndarray
    plane: np.ndarray

    @property
    def m(self) -> np.ndarray:
        """A·S (3 x 3)."""
        return self.a_axes * (1.0 + np.asarray(self.scale))[None, :]

    @property
    def k_matrix(self) -> np.ndarray:
        """K as a 3 x 3 matrix (zero diagonal), µm."""
        k = np.zeros((3, 3))
        for (i, j), v in zip(K_PAIRS, self.k_um):
            k[i, j] = v
        return k

    @property
    def normal(self) -> np.ndarray:
        """Unit upward normal (−a, −b, 1)/|·| of the workpiece plane, OM frame."""
        n = np.array([-self.plane[0], -self.plane[1], 1.0])
        return n / np.linalg.norm(n)


def tip_pm(model: PMModel, c_cmd_um: np.ndarray) -> np.ndarray:
    """Tool-tip positions (PM frame, µm) for commanded positions ``c_cmd_um`` (N, 3)."""
    c = np.asarray(c_cmd_um, float)
    u2 = (c / STRAIGHTNESS_REF_UM) ** 2
    return c @ model.m.T + u2 @ model.k_matrix.T + model.o_um


def tip_om(model: PMModel, c_cmd_um: np.ndarray) -> np.ndarray:
    """Tool-tip positions (OM frame, µm) for commanded positions (N, 3)."""
    return tip_pm(model, c_cmd_um) @ model.r_pose.T + model.t_um


def surface_target_om(model: PMModel, xy_om_um: np.ndarray, depth_um: float) -> np.ndarray:
    """Tip goal (OM frame, µm): the target lifted onto the plane and pushed ``depth_um`` along the inward normal."""
    xy = np.asarray(xy_om_um, float)
    a, b, c = model.plane
    s = np.column_stack([xy[:, 0], xy[:, 1], a * xy[:, 0] + b * xy[:, 1] + c])
    return s - depth_um * model.normal


def command_for_targets(model: PMModel, xy_om_um: np.ndarray, depth_um: float,
                        tol_um: float = 1e-7, max_iter: int = 50) -> np.ndarray:
    """Exact inverse: stage commands (µm, (N, 3)) whose tip lands on the goals of ``surface_target_om``.

    Newton's method on ``p(c) = p_goal`` with the analytic Jacobian ``A·S + 2·K·diag(c)/L²``.
    """
    goal = (surface_target_om(model, xy_om_um, depth_um) - model.t_um) @ model.r_pose
    m, k = model.m, model.k_matrix
    c = np.linalg.solve(m, (goal - model.o_um).T).T
    for _ in range(max_iter):
        f = tip_pm(model, c) - goal
        if np.max(np.abs(f)) < tol_um:
            break
        jac = m[None] + 2 * k[None] * (c[:, None, :] / STRAIGHTNESS_REF_UM ** 2)
        c = c - np.linalg.solve(jac, f[..., None])[..., 0]
    return c


#: the keys ``model_to_dict`` writes (calibration.json and truth.json share them)
PARAM_KEYS = ("scale_x_ppm", "scale_y_ppm", "scale_z_ppm", "nonorth_xy_urad", "nonorth_xz_urad", "nonorth_yz_urad",
              "axes_matrix", "straightness_um", "straightness_pairs", "straightness_ref_um", "offset_um", "R",
              "rotvec_urad", "R_angles_urad", "T_um", "plane_a", "plane_b", "plane_c_um", "plane_tilt_x_urad",
              "plane_tilt_y_urad", "normal")


def model_to_dict(model: PMModel) -> dict:
    """The parameters with their units as a JSON-able dict (keys ``PARAM_KEYS``).

    ``R_angles_urad`` are the x-y-z Euler angles (R = Rz·Ry·Rx) in µrad; ``rotvec_urad`` the rotation vector.
    """
    no = nonorthogonality_rad(model.a_axes) * 1e6
    r = model.r_pose
    ang = np.array([np.arctan2(r[2, 1], r[2, 2]), -np.arcsin(np.clip(r[2, 0], -1, 1)), np.arctan2(r[1, 0], r[0, 0])])
    return {
        "scale_x_ppm": float(model.scale[0] * 1e6), "scale_y_ppm": float(model.scale[1] * 1e6),
        "scale_z_ppm": float(model.scale[2] * 1e6),
        "nonorth_xy_urad": float(no[0]), "nonorth_xz_urad": float(no[1]), "nonorth_yz_urad": float(no[2]),
        "axes_matrix": np.asarray(model.a_axes).tolist(),
        "straightness_um": [float(v) for v in model.k_um],
        "straightness_pairs": ["%s(%s)" % ("xyz"[i], "xyz"[j]) for i, j in K_PAIRS],
        "straightness_ref_um": STRAIGHTNESS_REF_UM,
        "offset_um": [float(v) for v in model.o_um],
        "R": np.asarray(r).tolist(), "rotvec_urad": [float(v) for v in matrix_to_rotvec(r) * 1e6],
        "R_angles_urad": [float(v) for v in ang * 1e6],
        "T_um": [float(v) for v in model.t_um],
        "plane_a": float(model.plane[0]), "plane_b": float(model.plane[1]), "plane_c_um": float(model.plane[2]),
        "plane_tilt_x_urad": float(np.arctan(model.plane[0]) * 1e6),
        "plane_tilt_y_urad": float(np.arctan(model.plane[1]) * 1e6),
        "normal": [float(v) for v in model.normal],
    }


def model_from_dict(d: dict) -> PMModel:
    """Inverse of ``model_to_dict`` (raises KeyError/ValueError/TypeError on a malformed dict)."""
    a = np.array(d["axes_matrix"], float).reshape(3, 3)
    scale = np.array([d["scale_x_ppm"], d["scale_y_ppm"], d["scale_z_ppm"]], float) * 1e-6
    k = np.array(d["straightness_um"], float).reshape(6)
    if float(d.get("straightness_ref_um", STRAIGHTNESS_REF_UM)) != STRAIGHTNESS_REF_UM:
        raise ValueError("straightness_ref_um differs from this version's")
    r = np.array(d["R"], float).reshape(3, 3)
    m = PMModel(a, scale, k, np.array(d["offset_um"], float).reshape(3), r, np.array(d["T_um"], float).reshape(3),
                np.array([d["plane_a"], d["plane_b"], d["plane_c_um"]], float))
    if not all(np.all(np.isfinite(v)) for v in (a, scale, k, r, m.o_um, m.t_um, m.plane)):
        raise ValueError("non-finite parameter")
    return m


def landing_errors(true_model: PMModel, xy_om_um: np.ndarray, depth_um: float, c_cmd_um: np.ndarray):
    """Where commands land on the true machine.

    Returns
    -------
    lateral_um : (N,) distance in the plane perpendicular to the true normal between the tip and its goal.
    depth_err_um : (N,) tip depth below the true surface along the true normal minus ``depth_um``.
    """
    tip = tip_om(true_model, c_cmd_um)
    goal = surface_target_om(true_model, xy_om_um, depth_um)
    n = true_model.normal
    e = tip - goal
    along = e @ n
    lateral = np.linalg.norm(e - along[:, None] * n, axis=1)
    return lateral, -along
