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
