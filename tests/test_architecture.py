"""The house rules of docs/architecture.md that a machine can check (the floors themselves: `lint-imports`,
run by scripts/test.sh with the contracts in pyproject.toml)."""

from __future__ import annotations

import ast
from pathlib import Path

import grimp
import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "workbench"


def _modules():
    for f in sorted(PACKAGE.rglob("*.py")):
        yield f, ast.parse(f.read_text(encoding="utf-8"), filename=str(f))


def test_no_private_name_is_imported_from_another_module():
    found = []
    for f, tree in _modules():
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.level > 0 or (node.module or "").startswith("workbench")):
                found += [f"{f.relative_to(ROOT)}:{node.lineno} imports {a.name} from {'.' * node.level}{node.module}"
                          for a in node.names if a.name.startswith("_") and not a.name.startswith("__")]
    assert not found, "private names imported across modules:\n" + "\n".join(found)


def test_no_import_cycle_between_modules():
    """Not even one hidden by an import inside a function: two modules that need each other share a third."""
    g = grimp.build_graph("workbench", cache_dir=None)
    cycles = sorted({tuple(sorted((m, b))) for m in g.modules for b in g.find_modules_directly_imported_by(m)
                     if g.find_shortest_chain(importer=b, imported=m)})
    assert not cycles, "modules that import each other (directly or through others):\n" + "\n".join(map(str, cycles))


def test_the_checks_find_what_they_look_for(tmp_path):
    """The two checks above are not vacuous: they see a private import and a cycle where there is one."""
    tree = ast.parse("from .match import _overlap\nfrom .match import overlap\n")
    names = [a.name for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) for a in n.names]
    assert [n for n in names if n.startswith("_")] == ["_overlap"]
    pkg = tmp_path / "cyc"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from . import b\n")
    (pkg / "b.py").write_text("def f():\n    from . import a\n")
    import sys

    sys.path.insert(0, str(tmp_path))
    try:
        g = grimp.build_graph("cyc", cache_dir=None)
    finally:
        sys.path.remove(str(tmp_path))
    assert g.find_shortest_chain(importer="cyc.b", imported="cyc.a") == ("cyc.b", "cyc.a")


@pytest.mark.parametrize("limit_lines", [700])
def test_modules_stay_small(limit_lines):
    big = [(f.relative_to(ROOT), n) for f, _ in _modules() if (n := len(f.read_text().splitlines())) > limit_lines]
    assert not big, f"modules over {limit_lines} lines: {big}"


def test_functions_stay_short():
    long_ = []
    for f, tree in _modules():
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > 120:
                    long_.append(f"{f.relative_to(ROOT)}:{node.lineno} {node.name} ({n} lines)")
    assert not long_, "functions over 120 lines:\n" + "\n".join(long_)
