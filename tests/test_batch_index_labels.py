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
