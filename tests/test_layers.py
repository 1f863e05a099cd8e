"""The package's layers: the shared core (``toolkit.common``) imports no workflow, the two
workflows (``static``, ``impact``) never import each other, and meshing (``toolkit.mesh``)
imports neither workflow; only the command line (``toolkit.cli``) sees everything. Every import
counts, those inside functions too."""

import ast
from pathlib import Path

import pytest

import toolkit

PACKAGE = Path(toolkit.__file__).parent

#: layer -> layers it must not import
FORBIDDEN = {
    "common": {"static", "impact", "mesh", "cli"},
    "static": {"impact", "cli"},
    "impact": {"static", "cli"},
    "mesh": {"static", "impact", "cli"},
}


def _layer(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "toolkit" else None


def _imports(path: Path) -> list[tuple[int, str]]:
    """``(line, module)`` of every toolkit import in ``path``, at any depth."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found += [(node.lineno, node.module)] + [(node.lineno, f"{node.module}.{a.name}") for a in node.names]
        elif isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names]
    return [(line, m) for line, m in found if m.startswith("toolkit.")]


def _violations(root: Path) -> list[str]:
    out = []
    for path in sorted(root.rglob("*.py")):
        layer = path.relative_to(root).parts[0] if len(path.relative_to(root).parts) > 1 else None
        for line, module in _imports(path):
            if _layer(module) in FORBIDDEN.get(layer, ()):
                out.append(f"{path.relative_to(root.parent)}:{line} ({layer}) imports {module}")
    return sorted(set(out))


def test_no_layer_imports_what_it_must_not():
    assert _violations(PACKAGE) == []


def test_the_check_finds_an_import_inside_a_function(tmp_path):
    """The walk sees an import inside a function body, where a module-level scan would not."""
    pkg = tmp_path / "toolkit"
    (pkg / "mesh").mkdir(parents=True)
    (pkg / "mesh" / "x.py").write_text("def f():\n    from toolkit.static.plan import SurgicalPlan\n")
    (pkg / "common").mkdir()
    (pkg / "common" / "y.py").write_text("import numpy\nfrom toolkit.common import mesh\n")
    assert _violations(pkg) == ["toolkit/mesh/x.py:2 (mesh) imports toolkit.static.plan",
                                "toolkit/mesh/x.py:2 (mesh) imports toolkit.static.plan.SurgicalPlan"]


@pytest.mark.parametrize("module, layer", [("toolkit.static.plan", "static"), ("toolkit", None), ("numpy", None)])
def test_layer_of_a_module(module, layer):
    assert _layer(module) == layer
