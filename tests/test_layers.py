"""Architecture: imports point down only (control <- sim <- study); matplotlib only in plot."""

import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1] / "aocontrol"
CONTROL = ["plant.py", "controllers", "analysis", "synthesis", "disturbance.py", "_validation.py"]


def _imports(path: pathlib.Path) -> set[str]:
    tree = ast.parse(path.read_text())
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
    return out


def _files(entries):
    for e in entries:
        p = ROOT / e
        if p.is_dir():
            yield from sorted(p.rglob("*.py"))
        elif p.exists():
            yield p


@pytest.mark.parametrize("path", list(_files(CONTROL)), ids=lambda p: str(p.relative_to(ROOT)))
def test_control_layer_imports_no_sim_or_study(path):
    bad = {m for m in _imports(path) if m.startswith(("aocontrol.sim", "aocontrol.study"))}
    assert not bad, f"{path} imports {bad}"


@pytest.mark.parametrize("path", list(_files(["sim"])), ids=lambda p: str(p.relative_to(ROOT)))
def test_sim_layer_imports_no_study(path):
    bad = {m for m in _imports(path) if m.startswith("aocontrol.study")}
    assert not bad, f"{path} imports {bad}"


def test_only_plot_module_imports_matplotlib():
    users = {
        p.relative_to(ROOT).as_posix()
        for p in ROOT.rglob("*.py")
        if any(m.startswith("matplotlib") for m in _imports(p))
    }
    assert users == {"study/plot.py"}, users
