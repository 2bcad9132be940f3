"""Progress lines: the single commands' ``say`` receives the report writers' figure lines; silence.py's gap."""
from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

from markcal.pipeline.progress import progress
from markcal.reports import html

ROOT = Path(__file__).resolve().parents[1]


def _draw_one() -> None:
    fig = html.new_figure(2.0, 1.5)
    fig.add_subplot(111).plot([0, 1], [0, 1])
    html.png_b64(fig)


@pytest.fixture
def every_figure(monkeypatch):
    monkeypatch.setattr(html, "FIGURE_PROGRESS_EVERY_S", 0.0)
    yield
    html.figure_progress(None)


def test_progress_prints_the_report_figure_lines(capsys, every_figure):
    say = progress(False)
    say("writing tables and report")
    _draw_one()
    _draw_one()
    err = capsys.readouterr().err.splitlines()
    assert [re.sub(r"^\[\s*[\d.]+ s\] ", "", e) for e in err] == [
        "writing tables and report", "report: 1 figure drawn", "report: 2 figures drawn"]


def test_quiet_progress_prints_no_figure_lines(capsys, every_figure):
    progress(False)
    progress(True)                    # the later command's choice wins
    _draw_one()
    assert capsys.readouterr().err == ""


def test_silence_measures_start_to_exit_without_lines(tmp_path):
    spec = importlib.util.spec_from_file_location("silence", ROOT / "benchmarks" / "silence.py")
    silence = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(silence)
    r = silence.run_one(["--version"], str(tmp_path))       # prints its version on stdout, nothing on stderr
    assert r["status"] == 0 and r["lines"] == 0 and r["ends_with"] == "(exit)"
    assert r["gap"] == pytest.approx(r["wall"], abs=1e-9) and r["gap_cpu"] == pytest.approx(r["cpu"], abs=1e-9)
    assert 0 < r["cpu"] < 60
