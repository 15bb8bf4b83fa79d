"""Notebooks run top to bottom (code cells executed in order, as a newcomer would), in quick mode.

Each notebook reads ``AOCONTROL_NOTEBOOK_QUICK=1`` to keep its runs small; it runs in a temporary
folder (the files it writes land there). The notebooks assert their own conclusions (e.g. the
data-driven controller beats the integrator in closed loop), so a notebook that rots fails here.
"""

import json
import pathlib

import matplotlib
import pytest

NOTEBOOKS = sorted((pathlib.Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


def _run(path: pathlib.Path) -> dict:
    nb = json.loads(path.read_text())
    namespace: dict = {"__name__": "__notebook__"}
    n_code = 0
    for i, cell in enumerate(nb["cells"]):
        if cell["cell_type"] != "code":
            continue
        n_code += 1
        source = "".join(cell["source"])
        exec(compile(source, f"{path.name}[cell {i}]", "exec"), namespace)  # noqa: S102
    assert n_code > 0
    return namespace


def test_there_are_notebooks():
    assert len(NOTEBOOKS) >= 1


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_runs_top_to_bottom(path, tmp_path, monkeypatch):
    matplotlib.use("Agg")
    monkeypatch.setenv("AOCONTROL_NOTEBOOK_QUICK", "1")
    monkeypatch.chdir(tmp_path)
    namespace = _run(path)
    if "QUICK" in namespace:
        assert namespace["QUICK"] is True  # the notebook honoured the quick mode
    for png in tmp_path.glob("*.png"):  # every figure it wrote has content
        assert png.stat().st_size > 1000, png.name
