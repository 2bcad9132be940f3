"""One full-size plate (19 x 19 fiducials, ~5 M points): the issue's goals at full size."""
import numpy as np

from conftest import save_render
from markcal.fixtures.gls import correction_residual
from markcal.fixtures.scan_plate import ScanOptions, machine_from_truth, render_scan
from markcal.pipeline.flows.scan import ScanOptions as FlowOptions
from markcal.pipeline.flows.scan import run_scan
from markcal.stages.deviation import GridCorrection
from markcal.stages.plate import PlateSpec


def test_full_plate_meets_the_goals(tmp_path):
    spec = PlateSpec()
    r = render_scan(2024, spec, ScanOptions(n_contaminated=2, max_tilt_deg=3.0))
    cloud, _ = save_render(r, str(tmp_path))
    res = run_scan(cloud, spec, FlowOptions(orientation="upright"))     # no orientation mark: laid within +-15 deg
    # detection: >= 358 of 361 found and correctly indexed (2 are hidden under dirt)
    assert res.summary["n_detected"] >= 358
    assert set(res.missing_ids) == set(r.truth["hidden_ids"])
    t = r.truth["fiducials"]
    ids = res.fiducials["id"]
    true = np.column_stack([t["x_scanner_mm"], t["y_scanner_mm"], t["z_scanner_mm"]])[ids]
    got = np.column_stack([res.fiducials[k] for k in ("x_scanner_mm", "y_scanner_mm", "z_scanner_mm")])
    err = np.linalg.norm(got - true, axis=1)
    assert np.sqrt(np.mean(err ** 2)) <= 0.015 and err.max() <= 0.06
    # the loop: residual of the correction grid on the true machine, rigid part excluded
    grid = GridCorrection.from_nodes(res.grid_xy_mm, res.grid_dxy_mm)
    hx, hy = spec.half_extent_mm
    _, resid = correction_residual(machine_from_truth(r.truth), grid.command, hx, hy, 1.0)
    mag = np.hypot(*resid.T)
    assert np.sqrt(np.mean(mag ** 2)) <= 0.03 and mag.max() <= 0.10
    # the uncorrected field looks like the paper's: sub-mm to mm, larger in X than in Y
    s = res.summary
    assert 0.3 < s["rms_mm"] < 1.5 and s["rms_x_mm"] > s["rms_y_mm"]
