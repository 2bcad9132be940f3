"""Shared renders: small plates (7 x 7 fiducials) keep the suite fast."""
import os

import numpy as np
import pytest

from markcal.fixtures.scan_plate import ScanOptions, render_scan
from markcal.fixtures.scan_plate import plate_spec_toml
from markcal.stages.plate import DEFAULT_ORIENTATION_MARK, PlateSpec

SMALL = PlateSpec(rows=7, cols=7, orientation_mark=DEFAULT_ORIENTATION_MARK)


def save_render(render, folder, name="cloud.npy"):
    """Write a render's cloud (N x 4 NPY) and plate spec; return the paths."""
    os.makedirs(folder, exist_ok=True)
    cloud = os.path.join(folder, name)
    np.save(cloud, np.column_stack([render.xyz_mm, render.intensity]))
    plate = os.path.join(folder, "plate.toml")
    with open(plate, "w") as fh:
        fh.write(plate_spec_toml(render.spec))
    return cloud, plate


@pytest.fixture(scope="session")
def small_render():
    return render_scan(101, SMALL, ScanOptions(n_contaminated=1, z_convention="height"))


@pytest.fixture(scope="session")
def small_files(small_render, tmp_path_factory):
    return save_render(small_render, str(tmp_path_factory.mktemp("small")))


@pytest.fixture(scope="session")
def small_result(small_files):
    from markcal.pipeline.flows.scan import run_scan
    return run_scan(small_files[0], SMALL)
