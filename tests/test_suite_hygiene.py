"""Suite hygiene (issue 21): every ``pytest.raises`` says which error it expects."""
import ast
from pathlib import Path

TESTS = Path(__file__).resolve().parent


def _raises_without_match(path: Path) -> list:
    bad = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "raises"
                and isinstance(node.func.value, ast.Name) and node.func.value.id == "pytest"
                and not any(k.arg == "match" for k in node.keywords)):
            bad.append(f"{path.name}:{node.lineno}")
    return bad


def test_every_pytest_raises_has_match(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text("import pytest\nwith pytest.raises(ValueError):\n    pass\n"
                     "with pytest.raises(ValueError, match='x'):\n    pass\n")
    assert _raises_without_match(probe) == ["probe.py:2"]        # the checker itself finds one
    bad = [b for p in sorted(TESTS.glob("test_*.py")) for b in _raises_without_match(p)]
    assert not bad, "pytest.raises without match=: " + ", ".join(bad)
