"""Scans flattened line by line: the flatten recognised by its signature, each line's fit taken again from its
far field (``stages/indent_unflatten``)."""
from __future__ import annotations

import numpy as np
import pytest

from markcal.fixtures.indent_maps import render_afm
from markcal.fixtures.indent_single_ruled import render_single_ruled
from markcal.fixtures.line_flatten import flatten_lines
from markcal.stages.indent_unflatten import LineFlatten, Rounding, detect_line_flatten, unflatten_lines


def _flatten(z, how, axis=0):
    """Each line's fit taken off (:func:`markcal.fixtures.line_flatten.flatten_lines`), stored as float32."""
    return flatten_lines(z, how, axis).astype(np.float32)


def _pit_map(seed=0, n=200, depth_nm=800.0, noise_nm=0.5):
    """A tilted plane with one square pyramid pit (turned 10 degrees, 60 % of the field across), and noise."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:n, 0:n].astype(float)
    c, s = np.cos(np.radians(10)), np.sin(np.radians(10))
    u, v = (xx - 0.45 * n) * c + (yy - 0.55 * n) * s, -(xx - 0.45 * n) * s + (yy - 0.55 * n) * c
    half = 0.3 * n
    pit = -depth_nm * np.clip(1 - np.maximum(np.abs(u), np.abs(v)) / half, 0, None)
    return 0.4 * xx - 0.25 * yy + 30.0 + pit + rng.normal(0, noise_nm, (n, n))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_scans_as_drawn_are_not_taken_for_flattened(seed):
    """The independent renderer's scans and an array render as drawn: their lines' fits differ (noise over
    the square root of the width at least, tens of nm through an imprint)."""
    assert detect_line_flatten(render_single_ruled(seed, size_px=128).height_nm) is None
    assert detect_line_flatten(render_afm(1000 + seed).data) is None


@pytest.mark.parametrize("how,axis", [(0, 0), (1, 0), (2, 0), (3, 0), ("median", 0), (1, 1), ("median", 1)])
def test_each_line_flatten_is_recognised(how, axis):
    """Every row's (axis 1: column's) mean, median or polynomial of order 1-3 taken off, stored as float32;
    a least-squares flatten of order k is told from one of order k - 1 (it zeroes that fit too)."""
    z = _flatten(render_single_ruled(4, size_px=128).height_nm, how, axis)
    found = detect_line_flatten(z)
    assert found == LineFlatten(axis=axis, order=0 if how == "median" else how,
                                how="median" if how == "median" else "poly")


@pytest.mark.parametrize("how", [0, 1, "median"])
def test_a_flatten_stored_in_integer_steps_is_recognised(how):
    """Stored as integers of 0.2 nm (a 16-bit file over a 13 µm range rounds so): each line's mean moves by
    about 0.2 / sqrt(12 x 128) = 0.005 nm, under the 2 % of the noise (0.056 nm here) the lines must agree."""
    z = _flatten(render_single_ruled(4, size_px=128).height_nm, how).astype(float)
    found = detect_line_flatten(np.round(z / 0.2) * 0.2)
    assert found == LineFlatten(axis=0, order=0 if how == "median" else how,
                                how="median" if how == "median" else "poly")


def _written_with(z, digits):
    """Each height as a text export writes it, to ``digits`` significant digits (``-1.65E+00``)."""
    return np.array([float(f"{v:.{digits - 1}e}") for v in np.ravel(z)]).reshape(np.shape(z))


@pytest.mark.parametrize("order", [0, 1, 2, 3])
def test_a_flatten_written_to_three_digits_is_recognised_with_its_order(order):
    """Written to 3 significant digits, each height is off by up to half its last digit (0.005 nm near
    1 nm, 0.5 nm near 100 nm): the lines' fits scatter by more than 2 % of the noise. The agreement then
    allows 4 standard deviations of what that rounding gives each coefficient. Before, this seed read as
    no flatten (orders 0, 1) or as order 1 (orders 2, 3)."""
    z = _written_with(flatten_lines(render_single_ruled(4, size_px=128).height_nm, order), 3)
    assert Rounding.of(z).digits == 3
    assert detect_line_flatten(z) == LineFlatten(axis=0, order=order, how="poly")


def test_rounding_of_a_map_as_written():
    """Significant digits and a grid of integer steps are found; float32 values of any size have neither."""
    z = render_single_ruled(4, size_px=128).height_nm
    assert Rounding.of(z.astype(np.float32)) == Rounding(None, 0.0)
    assert Rounding.of(_written_with(z, 4)).digits == 4
    assert Rounding.of(np.round(z / 0.2) * 0.2).step_nm == pytest.approx(0.2, rel=1e-4)   # float32 heights


def test_a_plane_levelled_after_the_flatten_keeps_the_signature():
    """A plane levelled after the flatten adds a trend across the lines: still recognised."""
    z = _flatten(_pit_map(), 1).astype(float)
    yy, xx = np.mgrid[0:z.shape[0], 0:z.shape[1]]
    assert detect_line_flatten(z + 0.3 * yy - 5.0) == LineFlatten(axis=0, order=1, how="poly")


def test_a_plain_noisy_scan_is_not_taken_for_flattened():
    """A featureless tilted scan with white noise: its lines' means scatter by the noise over the square root
    of the width (here 0.06 of the noise): far above the rounding a flatten leaves, so no flatten."""
    rng = np.random.default_rng(7)
    yy, xx = np.mgrid[0:256, 0:256]
    assert detect_line_flatten(0.2 * xx + 0.1 * yy + rng.normal(0, 1.0, (256, 256))) is None


def test_blank_and_constant_maps_have_no_flatten():
    assert detect_line_flatten(np.zeros((64, 64))) is None
    assert detect_line_flatten(np.full((64, 64), np.nan)) is None


@pytest.mark.parametrize("how", [0, 1, "median"])
def test_unflatten_restores_the_map_up_to_a_plane(how):
    """A pit of 800 nm filling 60 % of the field, each row's fit taken off: the rows through it stand more than
    100 nm off; put back, the map is the original up to a plane within 1 % of the depth (the depth goal)."""
    z0 = _pit_map()
    z = _flatten(z0, how)
    u = unflatten_lines(z, detect_line_flatten(z)).z_nm

    def off_plane(a):
        yy, xx = np.mgrid[0:a.shape[0], 0:a.shape[1]]
        far = z0 - (0.4 * xx - 0.25 * yy + 30.0) > -1.0              # the original's far field
        m = np.column_stack([xx[far], yy[far], np.ones(far.sum())])
        coef = np.linalg.lstsq(m, (a - z0)[far], rcond=None)[0]
        return np.abs(a - z0 - (coef[0] * xx + coef[1] * yy + coef[2]))

    assert np.max(off_plane(z.astype(float))) > 100.0
    assert np.max(off_plane(u)) <= 8.0
