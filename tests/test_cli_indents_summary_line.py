"""The indents command's last progress line says what was judged, never 'None' (issue 20)."""
from __future__ import annotations

from markcal.fixtures.indent_single import SingleOptions, render_single, single_ibw
from markcal.pipeline.cli import main


def test_single_imprint_without_spec_says_nothing_was_judged(tmp_path, capsys):
    """No array spec: no tolerance, so the line says so instead of 'None out of tolerance'."""
    path = tmp_path / "one.ibw"
    path.write_bytes(single_ibw(render_single(2000, SingleOptions())))
    assert main(["indents", str(path), "--out", str(tmp_path / "o"), "--no-report"]) == 0
    out = capsys.readouterr()
    text = out.out + out.err
    assert "no array spec: nothing judged" in text
    assert "None" not in text


def test_report_without_spec_marks_nothing_out_of_tolerance(tmp_path):
    """Without a spec the nominal size is only inferred and nothing is judged: an imprint 0.2 µm off that
    inferred size (in_tolerance 0 in indents.csv) is drawn like the others, and no caption speaks of red; with
    a spec the same flags are drawn red."""
    import dataclasses

    import numpy as np

    from markcal.reports.indents_report import _judged
    from markcal.stages.indent_geometry import Imprint
    from markcal.pipeline.flows.indents import FileResult
    m = Imprint(x_um=1.0, y_um=1.0, diameter_um=2.2, diag1_um=2.2, diag2_um=2.2, depth_nm=float("nan"),
                hd_ratio=float("nan"), orientation_deg=0.0, pileup_nm=float("nan"), corners_um=np.zeros((4, 2)),
                fit_rms=0.0, n_pixels=100)
    f = FileResult(source="a.tif", kind="om", pixel_um=0.1, table={"in_tolerance": np.array([0, 1])},
                   imprints=[m, m], missing_ids=[], nominal_um=2.0, nominal_inferred=True, info={}, image=None)
    assert list(_judged(f)) == [1, 1]
    assert list(_judged(dataclasses.replace(f, nominal_inferred=False))) == [0, 1]
