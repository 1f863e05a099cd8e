"""The package's layers: the shared core (``toolkit.common``) imports no workflow, the two
workflows (``static``, ``impact``) never import each other, and meshing (``toolkit.mesh``)
imports neither workflow; only the command line (``toolkit.cli``) sees everything. No module
imports itself back through others (no cycle). Every import counts, those inside functions too;
imports under ``if TYPE_CHECKING:`` (annotations only, never executed) do not."""

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


def _type_checking_nodes(tree: ast.AST) -> set[int]:
    """``id`` of every node under an ``if TYPE_CHECKING:`` block of ``tree``."""
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and getattr(node.test, "id", getattr(node.test, "attr", None)) == "TYPE_CHECKING":
            out.update(id(n) for branch in node.body for n in ast.walk(branch))
    return out


def _imports(path: Path) -> list[tuple[int, str]]:
    """``(line, module)`` of every executed toolkit import in ``path``, at any depth; a
    ``from M import name`` gives both ``M`` and ``M.name`` (``name`` may be a submodule)."""
    found = []
    tree = ast.parse(path.read_text(), str(path))
    skip = _type_checking_nodes(tree)
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
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


def _module_name(path: Path, root: Path) -> str:
    parts = path.relative_to(root.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _graph(root: Path) -> dict[str, set[str]]:
    """Module -> the toolkit modules it imports (a name resolved to the longest module it names),
    leaving out a module's imports of its own parent packages, which Python runs first anyway."""
    paths = {_module_name(p, root): p for p in root.rglob("*.py")}
    graph = {}
    for name, path in paths.items():
        edges = set()
        for _, module in _imports(path):
            while module and module not in paths:
                module = module.rpartition(".")[0]
            if module and module != name and not name.startswith(module + "."):
                edges.add(module)
        graph[name] = edges
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, iterative)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is None:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        found.append(sorted(component))
            elif child not in index:
                index[child] = low[child] = len(index)
                stack.append(child)
                on_stack.add(child)
                work.append((child, iter(sorted(graph.get(child, ())))))
            elif child in on_stack:
                low[node] = min(low[node], index[child])
    return sorted(found)


def test_no_import_cycle():
    assert _cycles(_graph(PACKAGE)) == []


def test_the_check_finds_a_cycle_through_a_function_and_skips_type_checking(tmp_path):
    """``a`` imports ``b`` at the top and ``b`` imports ``a`` inside a function: a cycle. ``c``
    imports ``a`` only for annotations (under ``TYPE_CHECKING``), and ``a`` imports ``c``: none."""
    pkg = tmp_path / "toolkit"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("import toolkit.b\nfrom toolkit import c\n")
    (pkg / "b.py").write_text("def f():\n    from toolkit.a import x\n")
    (pkg / "c.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from toolkit.a import x\n")
    assert _cycles(_graph(pkg)) == [["toolkit.a", "toolkit.b"]]


@pytest.mark.parametrize("module, layer", [("toolkit.static.plan", "static"), ("toolkit", None), ("numpy", None)])
def test_layer_of_a_module(module, layer):
    assert _layer(module) == layer
