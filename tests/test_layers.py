"""Architecture: imports point down only (control <- sim <- study); matplotlib only in the plot
modules (``study/plot.py`` and its private ``study/_plot_*.py``); no private name imported from
another package.

Relative imports (``from ..sim import loop``) are resolved to absolute module names, so the
layering rule cannot be broken unseen; a synthetic module shows the check detects them.

Private names: a leading underscore means "free to change" within the namespace that owns it.
``aocontrol.analysis._margins`` is owned by ``aocontrol.analysis`` (any module of the analysis
may import it, nothing outside); ``aocontrol.plant._x`` by the module ``aocontrol.plant``;
``aocontrol._validation`` by ``aocontrol`` (the project's shared checks). What another package
needs is promoted to a documented name (e.g. ``aocontrol.analysis.winding_zeros``).
"""

from __future__ import annotations

import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1] / "aocontrol"
CONTROL = [
    "plant.py",
    "controllers",
    "analysis",
    "synthesis",
    "io",
    "disturbance.py",
    "adaptive",
    "_validation.py",
    "_deprecation.py",
    "_units.py",
]


def _module_name(path: pathlib.Path, root: pathlib.Path) -> tuple[str, bool]:
    """Dotted name of ``path`` under the package directory ``root``, and whether a package."""
    rel = path.relative_to(root.parent).with_suffix("")
    parts = list(rel.parts)
    is_package = parts[-1] == "__init__"
    if is_package:
        parts = parts[:-1]
    return ".".join(parts), is_package


def _imports(path: pathlib.Path, root: pathlib.Path = ROOT) -> set[str]:
    """Absolute names of every module ``path`` imports (relative imports resolved).

    ``from X import a`` yields ``X`` and ``X.a`` (``a`` may be a submodule), so
    ``from .. import sim`` inside ``aocontrol/analysis`` is seen as ``aocontrol.sim``.
    """
    tree = ast.parse(path.read_text())
    name, is_package = _module_name(path, root)
    package = name if is_package else name.rpartition(".")[0]
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                if node.level - 1 > len(parts) - 1:
                    raise ValueError(f"{path}: relative import beyond the top-level package")
                base = ".".join(parts[: len(parts) - (node.level - 1)])
                module = f"{base}.{node.module}" if node.module else base
            else:
                module = node.module or ""
            out.add(module)
            out.update(f"{module}.{a.name}" for a in node.names if a.name != "*")
    return out


def _files(entries):
    for e in entries:
        p = ROOT / e
        if p.is_dir():
            yield from sorted(p.rglob("*.py"))
        elif p.exists():
            yield p


def _violations(path: pathlib.Path, forbidden: tuple[str, ...], root=ROOT) -> set[str]:
    return {
        m for m in _imports(path, root) if any(m == f or m.startswith(f + ".") for f in forbidden)
    }


@pytest.mark.parametrize("path", list(_files(CONTROL)), ids=lambda p: str(p.relative_to(ROOT)))
def test_control_layer_imports_no_sim_or_study(path):
    bad = _violations(path, ("aocontrol.sim", "aocontrol.study"))
    assert not bad, f"{path} imports {bad}"


@pytest.mark.parametrize("path", list(_files(["sim"])), ids=lambda p: str(p.relative_to(ROOT)))
def test_sim_layer_imports_no_study(path):
    bad = _violations(path, ("aocontrol.study",))
    assert not bad, f"{path} imports {bad}"


def _private_owner(name: str) -> str | None:
    """The namespace owning the first private component of a dotted name, or None."""
    parts = name.split(".")
    for i, part in enumerate(parts):
        if part.startswith("_") and not (part.startswith("__") and part.endswith("__")):
            return ".".join(parts[:i])
    return None


def _private_breaches(path: pathlib.Path, root: pathlib.Path = ROOT) -> set[str]:
    """Private names ``path`` imports from outside the namespace that owns them."""
    module, _ = _module_name(path, root)
    out = set()
    for name in _imports(path, root):
        owner = _private_owner(name)
        if owner is not None and not (module == owner or module.startswith(owner + ".")):
            out.add(name)
    return out


@pytest.mark.parametrize("path", list(_files(["."])), ids=lambda p: str(p.relative_to(ROOT)))
def test_no_private_name_imported_from_another_package(path):
    bad = _private_breaches(path)
    assert not bad, f"{path} imports private names of another package: {sorted(bad)}"


@pytest.mark.parametrize(
    ("source", "expected"),
    [
        ("from aocontrol.analysis._margins import is_stable\n", "aocontrol.analysis._margins"),
        ("from ..analysis._psd import welch_psd\n", "aocontrol.analysis._psd"),
        ("from aocontrol.plant import _response\n", "aocontrol.plant._response"),
        ("import aocontrol.controllers._lqg\n", "aocontrol.controllers._lqg"),
    ],
)
def test_private_import_from_another_package_is_detected(tmp_path, source, expected):
    # A synthetic synthesis module that reaches into another package's private names: the
    # check must see it; its own package's private modules and the shared checks are fine.
    root = tmp_path / "aocontrol"
    pkg = root / "synthesis"
    pkg.mkdir(parents=True)
    (root / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    bad = pkg / "_bad.py"
    bad.write_text(source)
    assert expected in _private_breaches(bad, root=root)
    bad.write_text(
        "from ._armodel import _ar2_psd\nfrom aocontrol._validation import check_int\n"
        "from aocontrol.analysis import winding_zeros\n"
    )
    assert not _private_breaches(bad, root=root)


def _is_plot_module(rel: str) -> bool:
    """The plotting module and its private modules by topic (``study/_plot_*.py``)."""
    folder, _, name = rel.rpartition("/")
    return folder == "study" and (name == "plot.py" or name.startswith("_plot_"))


def _matplotlib_outside_plots(root: pathlib.Path = ROOT) -> set[str]:
    """Modules under ``root`` that import matplotlib and are not plot modules."""
    users = {
        p.relative_to(root).as_posix()
        for p in root.rglob("*.py")
        if any(m == "matplotlib" or m.startswith("matplotlib.") for m in _imports(p, root))
    }
    return {u for u in users if not _is_plot_module(u)}


def test_only_plot_modules_import_matplotlib():
    assert _matplotlib_outside_plots() == set()
    # The rule is not empty: the plots themselves import it.
    assert any("matplotlib" in _imports(p) for p in (ROOT / "study").glob("_plot_*.py"))


def test_matplotlib_outside_the_plot_modules_is_detected(tmp_path):
    # Twin: a synthetic tree with a plot module (allowed) and two modules that are not plot
    # modules (one in sim, one in study named like a plot but outside the rule's pattern).
    root = tmp_path / "aocontrol"
    for pkg in ("study", "sim"):
        (root / pkg).mkdir(parents=True)
        (root / pkg / "__init__.py").write_text("")
    (root / "__init__.py").write_text("")
    (root / "study" / "_plot_topic.py").write_text("import matplotlib.pyplot as plt\n")
    (root / "sim" / "bad.py").write_text("from matplotlib import pyplot\n")
    (root / "study" / "plotting.py").write_text("def f():\n    import matplotlib\n")
    assert _matplotlib_outside_plots(root) == {"sim/bad.py", "study/plotting.py"}
    (root / "sim" / "bad.py").write_text("import numpy\n")
    (root / "study" / "plotting.py").write_text("")
    assert _matplotlib_outside_plots(root) == set()


@pytest.mark.parametrize(
    ("source", "expected"),
    [
        ("from ..sim import loop\n", "aocontrol.sim"),
        ("from .. import sim\n", "aocontrol.sim"),
        ("from ..study.plot import plot_psd\n", "aocontrol.study.plot"),
        ("from aocontrol import sim\n", "aocontrol.sim"),
    ],
)
def test_relative_upward_import_is_detected(tmp_path, source, expected):
    # A synthetic control-layer module that breaks the rule with a relative import: the
    # check must see it (before, relative imports were ignored).
    pkg = tmp_path / "aocontrol" / "analysis"
    pkg.mkdir(parents=True)
    (tmp_path / "aocontrol" / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    bad = pkg / "_bad.py"
    bad.write_text(source)
    found = _violations(bad, ("aocontrol.sim", "aocontrol.study"), root=tmp_path / "aocontrol")
    assert expected in found, found
    # And a relative import that stays in the layer is not flagged.
    bad.write_text("from ._loop import loop_response\nfrom .. import plant\n")
    assert not _violations(bad, ("aocontrol.sim", "aocontrol.study"), root=tmp_path / "aocontrol")


def _module_graph(root: pathlib.Path = ROOT) -> dict[str, set[str]]:
    """Module -> the package modules it imports (anywhere in it: a function's import too).

    ``from X import a`` is an edge to ``X.a`` when that is a module of the package, else to
    ``X`` (a name defined in ``X``, e.g. its ``__init__``).
    """
    files = {_module_name(p, root)[0]: p for p in sorted(root.rglob("*.py"))}
    graph = {}
    for name, path in files.items():
        edges = set()
        for m in _imports(path, root):
            if m in files:
                # "from X import a": both X and X.a are listed; keep X.a if a module.
                parent = m.rpartition(".")[0]
                edges.add(m)
                if parent in files and m not in files:
                    edges.add(parent)
        # Drop the parent X of "from X import a" when X.a is the module imported.
        for m in list(edges):
            if any(e.startswith(m + ".") and e in _imports_of(path, root, m) for e in edges):
                edges.discard(m)
        edges.discard(name)
        graph[name] = edges
    return graph


def _imports_of(path: pathlib.Path, root: pathlib.Path, module: str) -> set[str]:
    """Names ``path`` imports as ``from module import ...`` (``module.name``)."""
    tree = ast.parse(path.read_text())
    out = set()
    name, is_package = _module_name(path, root)
    package = name if is_package else name.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - (node.level - 1)])
                mod = f"{base}.{node.module}" if node.module else base
            else:
                mod = node.module or ""
            if mod == module:
                # a name of the module itself (not a submodule) keeps the edge to it
                out.update(f"{mod}.{a.name}" for a in node.names)
    return out


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_circle():
    # Imports inside functions count: a circle made lazy is still one piece in the wrong place.
    assert _cycles(_module_graph()) == []


def test_import_circle_is_detected(tmp_path):
    # Twin: two synthetic modules that import each other (one inside a function).
    root = tmp_path / "aocontrol"
    pkg = root / "study"
    pkg.mkdir(parents=True)
    (root / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from aocontrol.study.b import f\n")
    (pkg / "b.py").write_text("def f():\n    from aocontrol.study.a import g\n")
    assert _cycles(_module_graph(root)) == [["aocontrol.study.a", "aocontrol.study.b"]]
    (pkg / "b.py").write_text("def f():\n    pass\n")
    assert _cycles(_module_graph(root)) == []


def test_ground_floor_imports_nothing_above_it():
    # The shared checks, deprecations, atomic writes and the version import no layer; the top
    # package hands out control-layer names only.
    ground = ["_validation.py", "_deprecation.py", "_atomic.py", "_version.py"]
    allowed = {"aocontrol._validation", "aocontrol._deprecation", "aocontrol._atomic"}
    for name in ground:
        mods = {m for m in _imports(ROOT / name) if m.startswith("aocontrol")}
        assert mods <= allowed, (name, mods - allowed)
    top = _violations(ROOT / "__init__.py", ("aocontrol.sim", "aocontrol.study"))
    assert not top, top
