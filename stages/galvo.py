"""Simplified post-objective galvo model, paper 004 eqs. (1)-(5).

theta are optical angles (twice the mechanical mirror angles alpha); d is the
distance from the X mirror to the plane centre, e the distance between the
mirror axes; z_s is the height of the target above the calibration plane.
All lengths in mm, angles in rad.
"""
from __future__ import annotations

import numpy as np


def forward(theta_x_rad, theta_y_rad, d_mm, e_mm, z_mm=0.0):
    """Task-space position reached by optical angles, eqs. (1)-(2).

    Returns
    -------
    x_mm, y_mm : ndarray
    """
    theta_x_rad = np.asarray(theta_x_rad, float)
    theta_y_rad = np.asarray(theta_y_rad, float)
    w = d_mm - np.asarray(z_mm, float)
    x = w * np.tan(theta_x_rad)
    y = (e_mm + w / np.cos(theta_x_rad)) * np.tan(theta_y_rad)
    return x, y


def inverse(x_mm, y_mm, d_mm, e_mm, z_mm=0.0):
    """Joint-space commands for a task-space target, eqs. (3)-(5).

    Returns
    -------
    alpha_x_rad, alpha_y_rad : ndarray
        Mechanical mirror angles (half the optical angles).
    dfr_mm : ndarray
        Dynamic focus displacement from its zero position.
    """
    x = np.asarray(x_mm, float)
    y = np.asarray(y_mm, float)
    w = d_mm - np.asarray(z_mm, float)
    lever = e_mm + np.sqrt(w * w + x * x)
    alpha_x = 0.5 * np.arctan2(x, w)
    alpha_y = 0.5 * np.arctan2(y, lever)
    dfr = np.sqrt(lever * lever + y * y) - (e_mm + w)
    return alpha_x, alpha_y, dfr
