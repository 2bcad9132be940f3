"""Every shell command in the README and docs/ runs as printed (issue 16: a copied command never fails).

Each ```sh block is run line by line, each file's blocks in order in one temporary folder (so a later
block can use what an earlier one made). Lines that are not ``markcal`` commands (``make``, ``pip``)
are not run: they install or test markcal itself. Exit status 0, or 4 (ran, out of tolerance), passes.
"""
from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
MARKCAL = [sys.executable, "-m", "markcal.pipeline.cli"]


def commands(path: Path) -> list:
    text = path.read_text(encoding="utf-8").split("<!-- end of the commands the tests run -->")[0]
    out = []
    for block in re.findall(r"```sh\n(.*?)```", text, re.S):
        for line in block.replace("\\\n", " ").splitlines():
            words = shlex.split(line, comments=True)
            if words and words[0] == "markcal":
                out.append(words)
    return out


def test_every_doc_has_commands_and_the_readme_covers_each_job():
    readme = {w[1] for w in commands(ROOT / "README.md")}
    assert {"scan", "grid", "indents", "selfcal", "path", "servo", "batch", "export", "inspect"} <= readme


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_doc_commands_run(doc, tmp_path):
    env = dict(os.environ, MPLBACKEND="Agg")
    for words in commands(doc):
        p = subprocess.run(MARKCAL + words[1:] + (["--quiet"] if _takes_quiet(words) else []), cwd=tmp_path,
                           capture_output=True, text=True, env=env, timeout=600)
        assert p.returncode in (0, 4), f"{doc.name}: {' '.join(words)}\n{p.stderr[-2000:]}"


def _takes_quiet(words) -> bool:
    return "--quiet" not in words and not any(w in ("--help", "--list", "--version") for w in words)
