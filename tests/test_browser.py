"""The batch index and a per-input report open in headless Chromium: no console errors,
summary table visible, every image loaded, every link resolves.

Needs Debian's ``chromium`` (``make test`` installs it when missing; a test never installs
packages). Without it the test is skipped on a developer's machine and fails in CI (``CI=true``),
where a missing browser is a broken setup, not a reason to test less.
"""
import contextlib
import os
import shutil
import subprocess
from urllib.parse import unquote, urlparse

import pytest

from markcal.fixtures.batch_mix import MixOptions, render_batch_mix
from markcal.pipeline.cli import main

CHROMIUM = "/usr/bin/chromium"


def _missing(what: str):
    msg = f"{what}: run `make test` (installs Debian's chromium when root) or install it by hand"
    if os.environ.get("CI", "").lower() in ("true", "1", "yes"):
        pytest.fail(f"CI: {msg}")
    pytest.skip(msg)


def _chromium() -> str:
    path = shutil.which("chromium") or (CHROMIUM if os.path.exists(CHROMIUM) else None)
    if not path:
        _missing("chromium is not installed")
    return path


@pytest.fixture(scope="module")
def batch_out(tmp_path_factory):
    d = str(tmp_path_factory.mktemp("mix") / "in")
    render_batch_mix(d, seed=5, options=MixOptions(n_scan=0, n_selfcal=1, n_servo=2, n_broken=1))
    out = str(tmp_path_factory.mktemp("out") / "out")
    assert main(["batch", d, "--out", out, "--workers", "2", "--quiet"]) == 3
    return out


def _check_page(pw_page, url):
    errors = []
    pw_page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    pw_page.on("pageerror", lambda e: errors.append(str(e)))
    pw_page.goto(url)
    pw_page.wait_for_load_state("load")
    assert errors == [], errors
    broken = pw_page.evaluate("Array.from(document.images).filter(i => !(i.complete && i.naturalWidth > 0))"
                              ".map(i => i.alt)")
    assert broken == [], broken
    n_img = pw_page.evaluate("document.images.length")
    hrefs = pw_page.evaluate("Array.from(document.querySelectorAll('a[href]')).map(a => a.href)")
    for h in hrefs:
        u = urlparse(h)
        if u.scheme == "file":
            assert os.path.exists(unquote(u.path)), h
        else:
            assert u.scheme == "" or h.startswith("#"), f"external link {h}"
    return n_img, hrefs


@contextlib.contextmanager
def _browser():
    """A headless Chromium driven by playwright (skipped, or failed in CI, when either is missing)."""
    exe = _chromium()
    try:
        from playwright import sync_api
    except ImportError:
        _missing("playwright is not installed (pip install -e '.[test]')")
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=exe, headless=True, args=["--no-sandbox"])
        try:
            yield browser
        finally:
            browser.close()


def test_index_and_report_in_chromium(batch_out):
    with _browser() as browser:
        page = browser.new_page()
        n_img, hrefs = _check_page(page, "file://" + os.path.join(batch_out, "index.html"))
        assert page.is_visible("table#summary")
        n_rows = page.evaluate("document.querySelectorAll('#summary tbody tr').length")
        assert n_rows == 4
        assert n_img >= 2                      # servo and selfcal trend plots
        reports = [h for h in hrefs if h.endswith("report.html")]
        assert len(reports) == 3               # every processed input links its report
        # sorting and filtering work in the page
        page.click("#summary th >> nth=3")
        page.select_option("#st", "error")
        assert page.evaluate("Array.from(document.querySelectorAll('#summary tbody tr'))"
                             ".filter(r => r.style.display !== 'none').length") == 1
        _check_page(browser.new_page(), reports[0])


def _first_screen(pw_page, url, selector):
    """Open ``url`` at 1400 × 900 and return whether ``selector`` lies wholly inside that first screen."""
    pw_page.set_viewport_size({"width": 1400, "height": 900})
    _check_page(pw_page, url)
    box = pw_page.locator(selector).first.bounding_box()
    return box is not None and box["y"] >= 0 and box["y"] + box["height"] <= 900


@pytest.fixture(scope="module")
def single_reports(batch_out, tmp_path_factory):
    """Reports of the single commands the batch does not run: scan, grid, indents, pmcal, export note,
    inspect, path, drift (every image loads, no console error, the verdict on the first screen)."""
    d = tmp_path_factory.mktemp("single")
    stage = os.path.join(batch_out, "selfcal", "session01")
    assert main(["export", "a3200", stage, "--out", str(d / "stage.cal"), "--quiet", "--operator", "QA"]) == 0
    assert main(["inspect", str(d / "stage.cal"), "--out", str(d / "ins"), "--quiet"]) == 0
    assert main(["render", "path", "--n", "40", "--seed", "1", "--out", str(d / "job"), "--quiet"]) == 0
    assert main(["path", str(d / "job" / "job.csv"), "--out", str(d / "path"), "--quiet"]) in (0, 4)
    assert main(["render", "pmcal", "--seed", "1", "--pose-grid", "3", "--out", str(d / "pm"), "--quiet"]) == 0
    assert main(["drift", str(d / "pm" / "drift.csv"), "--out", str(d / "drift"), "--quiet"]) == 0
    # one small render of each other flow: a 5 x 5 plate, a measured grid, one AFM imprint, a pmcal session
    assert main(["render", "scan", "--rows", "5", "--cols", "5", "--seed", "5", "--out", str(d / "plate"),
                 "--formats", "npy", "--quiet"]) == 0
    assert main(["scan", str(d / "plate" / "cloud.npy"), "--plate", str(d / "plate" / "plate.toml"),
                 "--out", str(d / "scan"), "--quiet"]) == 0
    assert main(["render", "grid", "--seed", "3", "--out", str(d / "g"), "--quiet"]) == 0
    assert main(["grid", str(d / "g" / "measured.csv"), "--out", str(d / "grid"), "--quiet"]) == 0
    assert main(["render", "afm", "--single", "--seed", "2", "--out", str(d / "afm"), "--quiet"]) == 0
    assert main(["indents", str(d / "afm" / "heights.ibw"), "--out", str(d / "indents"), "--quiet"]) == 0
    assert main(["pmcal", str(d / "pm"), "--out", str(d / "pmcal"), "--quiet"]) == 0
    return {"scan": (d / "scan" / "report.html", "#verdict"), "grid": (d / "grid" / "report.html", "#verdict"),
            "indents": (d / "indents" / "report.html", "#verdict"), "pmcal": (d / "pmcal" / "report.html", "#verdict"),
            "export note": (d / "stage.cal.html", ".prov"), "inspect": (d / "ins" / "report.html", ".prov"),
            "path": (d / "path" / "report.html", "#verdict"), "drift": (d / "drift" / "report.html", ".prov"),
            "selfcal (batch)": (os.path.join(stage, "report.html"), "#verdict"),
            "servo (batch)": (os.path.join(batch_out, "servo", "trace01", "report.html"), "#verdict")}


def test_every_report_kind_shows_verdict_or_provenance_on_the_first_screen(single_reports):
    with _browser() as browser:
        off = [kind for kind, (path, sel) in single_reports.items()
               if not _first_screen(browser.new_page(), "file://" + str(path), sel)]
    assert off == [], f"verdict / provenance not on the first 1400 x 900 screen: {off}"


def test_dump_dom_of_index(batch_out):
    exe = _chromium()
    r = subprocess.run([exe, "--headless", "--no-sandbox", "--disable-gpu", "--dump-dom",
                        "file://" + os.path.join(batch_out, "index.html")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert 'id="summary"' in r.stdout and "rows shown" in r.stdout
