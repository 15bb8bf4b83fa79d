"""Structure of :mod:`aocontrol.sim.wfs`: no import circle; the sensors' shared interface.

Import circle: every import of every module of the package, at its top or inside a function
(an import deferred into a function hides a circle without removing it), read from the source
with :mod:`ast`; a synthetic package shows that the check sees a circle closed inside a
function.
"""

from __future__ import annotations

import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1] / "aocontrol"
WFS = ROOT / "sim" / "wfs"


def _module_name(path: pathlib.Path, root: pathlib.Path) -> str:
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _import_graph(package: pathlib.Path, root: pathlib.Path) -> dict[str, set[str]]:
    """``{module: modules of the package it imports}`` (absolute or relative, any depth).

    ``from P import n`` is an edge to ``P.n`` when that is a module of the package, else to
    ``P`` (importing a name of ``P`` runs ``P``).
    """
    paths = sorted(package.rglob("*.py"))
    names = {_module_name(p, root): p for p in paths}
    graph: dict[str, set[str]] = {}
    for name, path in names.items():
        is_package = path.name == "__init__.py"
        base_parts = name.split(".") if is_package else name.split(".")[:-1]
        edges = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                module = node.module or ""
                if node.level:
                    parts = base_parts[: len(base_parts) - (node.level - 1)]
                    module = ".".join(parts + ([module] if module else []))
                targets = [
                    f"{module}.{a.name}" if f"{module}.{a.name}" in names else module
                    for a in node.names
                ]
            else:
                continue
            edges.update(t for t in targets if t in names and t != name)
        graph[name] = edges
    return graph


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One circle through each module that lies on one (depth-first search)."""
    found, state = [], {}

    def visit(node: str, stack: list[str]) -> None:
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == "open":
                found.append(stack[stack.index(nxt) :] + [nxt])
            elif nxt not in state:
                visit(nxt, stack)
        stack.pop()
        state[node] = "done"

    for node in sorted(graph):
        if node not in state:
            visit(node, [])
    return found


def test_wfs_package_has_no_import_circle():
    graph = _import_graph(WFS, ROOT)
    assert "aocontrol.sim.wfs.sensors" in graph and graph["aocontrol.sim.wfs"]  # read them
    assert _circles(graph) == []


def test_circle_check_sees_an_import_inside_a_function(tmp_path):
    # The twin that must fail: b imports a at its top, a imports b inside a function (the
    # shape of the former back-compatibility __getattr__ of calibration.py).
    pkg = tmp_path / "pkg" / "wfs"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("from pkg.wfs.b import B\n")
    (pkg / "a.py").write_text("def __getattr__(name):\n    from pkg.wfs.b import B\n    return B\n")
    (pkg / "b.py").write_text("from . import a\n\nB = 1\n")
    circles = _circles(_import_graph(pkg, tmp_path / "pkg"))
    assert [sorted(set(c)) for c in circles] == [["pkg.wfs.a", "pkg.wfs.b"]]


def test_former_name_warns_with_the_release_that_removes_it():
    import aocontrol.sim.wfs as wfs

    match = r"LinearModalWFS is deprecated and will be removed in 0\.2\.0: use aocontrol\.sim\."
    with pytest.warns(DeprecationWarning, match=match):
        assert wfs.LinearModalWFS is wfs.LinearModalSensor
    with pytest.raises(AttributeError, match="has no attribute 'LinearModalWFZ'"):
        _ = wfs.LinearModalWFZ
