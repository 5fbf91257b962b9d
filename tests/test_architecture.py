"""The house rules of the layout (issue 14): a numeric core that knows no file format, no CLI
code used as a library, estimators as stages rather than string-compared variants."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PKG = REPO / "service" / "bmsid"
MAX_ESTIMATE_LINES = 400


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
    return out


def _py(*dirs: Path) -> list[Path]:
    return sorted(p for d in dirs for p in d.rglob("*.py"))


@pytest.mark.parametrize("core", ["model", "estimate"])
def test_numeric_core_does_not_import_the_config_format(core: str) -> None:
    bad = {
        str(p.relative_to(REPO)): sorted(m for m in _imports(p) if m.startswith("bmsid.config"))
        for p in _py(PKG / core)
    }
    assert not {k: v for k, v in bad.items() if v}


def test_nothing_outside_cli_imports_cli() -> None:
    files = [p for p in _py(PKG, REPO / "bench", REPO / "scripts") if "cli" not in p.parts]
    bad = [str(p.relative_to(REPO)) for p in files if any(
        m == "bmsid.cli" or m.startswith("bmsid.cli.") for m in _imports(p))]  # fmt: skip
    assert not bad


def test_estimate_modules_stay_small() -> None:
    sizes = {p.name: len(p.read_text(encoding="utf-8").splitlines()) for p in _py(PKG / "estimate")}
    assert max(sizes.values()) <= MAX_ESTIMATE_LINES, sizes


def test_variants_are_compositions_not_string_comparisons() -> None:
    pattern = re.compile(r"variant\s*[!=]=|[!=]=\s*[\"'](non-)?hy-affrls")
    hits = [
        f"{p.name}:{n}"
        for p in _py(PKG / "estimate")
        for n, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1)
        if pattern.search(line)
    ]
    assert not hits
