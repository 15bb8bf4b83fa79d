"""Notebooks: their sources, checked without running them.

The suite runs each notebook once, in the documentation build (tests/test_docs.py): myst-nb
executes it top to bottom in quick mode (``AOCONTROL_NOTEBOOK_QUICK=1``, set by docs/conf.py)
in a temporary folder, stops the build on an error (the notebooks assert their own conclusions,
e.g. the data-driven controller beats the integrator in closed loop, so a notebook that rots
fails there), and test_docs checks the executed copies: every cell ran in order, no error, no
RuntimeWarning from aocontrol. Running them here as well doubled their cost (about 95 s).
"""

import json
import pathlib
import re

import pytest

NOTEBOOKS = sorted((pathlib.Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))
# The one way a notebook reads its quick mode (docs/conf.py sets the variable for the build).
QUICK_LINE = re.compile(r'^QUICK = os\.environ\.get\("AOCONTROL_NOTEBOOK_QUICK"\) == "1"$', re.M)


def _code(path: pathlib.Path) -> list[str]:
    nb = json.loads(path.read_text())
    return ["".join(c["source"]) for c in nb["cells"] if c["cell_type"] == "code"]


def test_there_are_notebooks():
    assert len(NOTEBOOKS) >= 1


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_is_stored_without_outputs_and_compiles(path):
    nb = json.loads(path.read_text())
    code = [c for c in nb["cells"] if c["cell_type"] == "code"]
    assert code
    assert all(not c.get("outputs") and c.get("execution_count") is None for c in code)
    for i, source in enumerate(_code(path)):
        compile(source, f"{path.name}[cell {i}]", "exec")


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_reads_the_quick_switch(path):
    # A notebook that uses QUICK defines it once, from the variable the build sets: a typo
    # there would run the full-size notebook in the docs build.
    source = "\n".join(_code(path))
    if re.search(r"\bQUICK\b", source):
        assert len(QUICK_LINE.findall(source)) == 1, path.name
