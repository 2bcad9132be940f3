"""Hard OM array renders written as files, and their errors against truth (shared by the OM array tests)."""
from __future__ import annotations

import os

import numpy as np

from markcal.fixtures.indent_maps import array_toml, tiff_bytes
from markcal.fixtures.indent_micrograph import MicrographOptions, render_micrograph


def write_hard_array(folder, seed: int, d_um: float, na: float | None = 0.9):
    """A 3 x 3 hard OM array at 8 µm (280 x 280 px at 0.1 µm; lines, one-sided shading, halo; Airy ``na`` or
    the Gaussian blur) as ``om.tif`` and ``a.toml`` in ``folder``; returns their paths and the truth's imprints."""
    os.makedirs(folder, exist_ok=True)
    r = render_micrograph(seed, MicrographOptions(rows=280, cols=280, grid=(3, 3, 8.0), d_um=d_um, na=na))
    path, spec = os.path.join(folder, "om.tif"), os.path.join(folder, "a.toml")
    with open(path, "wb") as fh:
        fh.write(tiff_bytes(r.data, r.pixel_um))
    with open(spec, "w") as fh:
        fh.write(array_toml(3, 3, 8.0, d_um))
    return path, spec, r.truth["imprints"]


def errors_nm(table, truth) -> np.ndarray:
    """(n, 3) x, y and diameter errors (nm) of the measured imprint nearest each true one."""
    e = []
    for ti in truth:
        k = int(np.argmin(np.hypot(table["x_um"] - ti["x_um"], table["y_um"] - ti["y_um"])))
        e.append((table["x_um"][k] - ti["x_um"], table["y_um"][k] - ti["y_um"], table["diameter_um"][k] - ti["d_um"]))
    return 1000 * np.array(e)
