"""The batch index names failed checks by their captions with units, not by summary keys."""
from markcal.pipeline.batch import FlowColumns
from markcal.reports.batch_index import _readable_checks


def test_failed_checks_read_as_captions():
    cols = FlowColumns(("rms_mm", "n_detected"), (("rms_mm", "scan deviation RMS, mm"),),
                       ("scan deviation RMS, mm", "fiducials found"))
    assert (_readable_checks("rms_mm 0.2264 > 0.05; n_detected >= 40", cols)
            == "scan deviation RMS, mm 0.2264 > 0.05; fiducials found ≥ 40")
    assert _readable_checks("unknown_key <= 3", cols) == "unknown_key ≤ 3"     # undeclared keys stay as they are
    assert _readable_checks("", cols) == "" and _readable_checks("rms_mm <= 1", None) == "rms_mm <= 1"


def _rec(name, kind, checks, failed="", status="pass", **vals):
    return {"name": name, "group": "m", "flow": "scan", "status": status, "checks": checks, "failed_checks": failed,
            "kind": kind, "input_mtime": name, "reason": "", "report": "", "out_dir": name, "input": name, **vals}


CAL = "predicted_residual_rms_mm <= 0.071; cv_rmse_mm <= 0.047; n_missing <= 0"
VAL = "rms_mm <= 0.071; max_mm <= 0.252"
SCAN = FlowColumns(("kind", "rms_mm", "predicted_residual_rms_mm"),
                   (("predicted_residual_rms_mm", "predicted residual, mm"), ("rms_mm", "deviation RMS, mm")),
                   ("purpose", "deviation RMS, mm", "predicted residual, mm"))


def test_each_input_shows_the_figure_its_purpose_is_judged_on():
    from markcal.reports.batch_index import _main_figure, _tolerance_line
    cal = _rec("a", "calibration", CAL, rms_mm=0.4, predicted_residual_rms_mm=1e-4)
    val = _rec("b", "validation", VAL, "rms_mm 0.09 > 0.071", "fail", rms_mm=0.09)
    assert _main_figure(cal, {"scan": SCAN}) == ("predicted residual, mm", 1e-4)
    assert _main_figure(val, {"scan": SCAN}) == ("deviation RMS, mm", 0.09)
    assert _main_figure(dict(cal, status="error"), {"scan": SCAN}) == ("", None)
    line = _tolerance_line([cal, val], SCAN)
    assert "<li>calibration: predicted residual, mm ≤ 0.071" in line and "<li>validation: deviation RMS, mm ≤ 0.071" in line
    assert _tolerance_line([cal], SCAN) == "<p>tolerance: predicted residual, mm ≤ 0.071; cv_rmse_mm ≤ 0.047; n_missing ≤ 0</p>"


def test_trend_draws_inputs_of_the_other_purpose_hollow():
    from markcal.reports.batch_index import _trend_plot
    recs = [_rec("a", "calibration", CAL, rms_mm=0.4), _rec("b", "validation", VAL, rms_mm=0.01)]
    html = _trend_plot("scan", "rms_mm", "deviation RMS, mm", recs, SCAN.key_figures)
    assert "Hollow: an input whose verdict does not use this figure" in html
    one = _trend_plot("scan", "rms_mm", "deviation RMS, mm", recs[1:], SCAN.key_figures)
    assert "<img" in one and "Hollow" not in one


def test_input_time_is_the_datas_own_timestamp_when_there_is_one(tmp_path):
    import numpy as np
    import tifffile
    from markcal.pipeline.registry import data_time
    from markcal.reports.batch_index import _input_time
    p = tmp_path / "a.tif"
    tifffile.imwrite(p, np.zeros((4, 4), np.uint8), datetime="2024:03:05 14:15:16")
    assert data_time(p) == "2024-03-05T14:15:16"
    tifffile.imwrite(tmp_path / "b.tif", np.zeros((4, 4), np.uint8), datetime=False)
    assert data_time(tmp_path / "b.tif") is None and data_time(tmp_path) is None
    (tmp_path / "c.tif").write_bytes(b"II*\0garbage")
    assert data_time(tmp_path / "c.tif") is None                       # unreadable header: no timestamp
    rec = _rec("a", "calibration", CAL)
    assert _input_time(rec) == "a" and _input_time(dict(rec, data_time="2024-03-05T14:15:16")) == "2024-03-05T14:15:16"


def test_sem_image_time_from_its_fei_metadata():
    """The real SEM micrograph (../shared/realdata, vyastreb/sem2surface, BSD-3-Clause) says it was taken
    on 09/12/2023 at 05:00:10 PM in its FEI metadata."""
    from test_afm_readers import _real
    from markcal.pipeline.registry import data_time
    assert data_time(_real("sem_vickers/Indent_20230912_7kV_spot4.5_FOV100um_multiBSE_A_05.tif")) == "2023-09-12T17:00:10"
