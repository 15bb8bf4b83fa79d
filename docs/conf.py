"""Sphinx configuration of the aocontrol documentation (``make docs``).

Sources: the API from the docstrings (autodoc + numpydoc), the README's tour and its notes on
python-control (included, one source), the science cases table (generated from the case files
at build time), and the four notebooks of ``notebooks/``, executed at build time in their quick
mode (``AOCONTROL_NOTEBOOK_QUICK=1``, a few minutes on 2 cores) by myst-nb, so the rendered
pages carry their outputs and figures. The notebooks are stored without outputs; a notebook
that fails to run fails the build. No pandoc, no network.
"""

from __future__ import annotations

import os
import pathlib
import re
import shutil
import sys

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))  # document this checkout, installed or not

# The kernel that executes the notebooks inherits this environment: quick mode, headless
# matplotlib, and this checkout on the path.
os.environ["AOCONTROL_NOTEBOOK_QUICK"] = "1"
os.environ["PYTHONPATH"] = os.pathsep.join(
    [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])]
)

import aocontrol  # noqa: E402

project = "aocontrol"
author = "aocontrol developers"
copyright = "aocontrol developers, BSD-3-Clause"  # noqa: A001
version = release = aocontrol.__version__

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "numpydoc",
    "myst_nb",
]
source_suffix = {".rst": "restructuredtext", ".md": "myst-nb", ".ipynb": "myst-nb"}
exclude_patterns = ["_build", "jupyter_execute", "**.ipynb_checkpoints"]
root_doc = "index"

# API: numpydoc docstrings, members in source order, no class-member tables (they would need
# autosummary stubs), type hints left in the signatures.
autodoc_member_order = "bysource"
autodoc_default_options = {"members": True, "show-inheritance": False}
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False

# Notebooks: executed at build time in quick mode, in a temporary folder (the files they
# write do not land in the tree); an error stops the build.
nb_execution_mode = "force"
nb_execution_timeout = 900
nb_execution_in_temp = True
nb_execution_raise_on_error = True
nb_execution_show_tb = True
nb_merge_streams = True
myst_enable_extensions = ["dollarmath"]
myst_heading_anchors = 3

html_theme = "alabaster"
html_title = f"aocontrol {release}"
html_static_path: list[str] = []
html_theme_options = {
    "description": "Adaptive-optics control toolbox",
    "fixed_sidebar": True,
    "page_width": "1200px",  # the cases table and the code cells need the room
    "body_max_width": "none",
}


def _copy_notebooks() -> None:
    """The notebooks of ``notebooks/`` into ``docs/notebooks/`` (Sphinx reads only docs/)."""
    dst = HERE / "notebooks"
    dst.mkdir(exist_ok=True)
    for old in dst.glob("*.ipynb"):
        old.unlink()
    for nb in sorted((ROOT / "notebooks").glob("*.ipynb")):
        shutil.copy2(nb, dst / nb.name)


def _cases_table() -> None:
    """``docs/_generated/cases_table.md``: the science cases, from the case files themselves."""
    from aocontrol.study.cases import list_cases, load_case

    rows = [
        "| case | seeing | tau0 | G | J | stage 1: Hz / modes / latency [frame] "
        "| stage 2: Hz / modes / latency [frame] / WFS wavelength | vibration |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name in list_cases():
        c = load_case(name)
        s1, s2 = c.stage1, c.stage2
        vib = ", ".join(f"{f:g} Hz" for f in c.vibration.frequencies) if c.vibration else ""
        rows.append(
            f'| `{c.name}` ({c.title}) | {c.atmosphere.seeing:g}" | '
            f"{c.atmosphere.tau0 * 1e3:g} ms | {c.star.G:g} | {c.star.J:g} | "
            f"{s1.fs:g} / {s1.n_modes} / {s1.latency_frames:g} | "
            f"{s2.fs:g} / {s2.n_modes} / {s2.latency_frames:g} / {s2.wavelength * 1e6:g} um | "
            f"{vib} |"
        )
    out = HERE / "_generated"
    out.mkdir(exist_ok=True)
    text = "\n".join(rows) + "\n"
    target = out / "cases_table.md"
    if not target.exists() or target.read_text() != text:  # unchanged: no rebuild
        target.write_text(text)


# ``|x|`` (an absolute value, natural in a numerical docstring) is a substitution reference to
# reStructuredText: outside inline literals and roles it is escaped to a literal ``\|x\|``.
_LITERAL = re.compile(r"(``.*?``|:\w+:`[^`]*`|`[^`]*`_?)")
_BARS = re.compile(r"(?<![\\|])\|([^|\s`][^|`]*?)\|(?![|_])")


def _escape_bars(app, what, name, obj, options, lines):  # noqa: ARG001 - Sphinx signature
    for i, line in enumerate(lines):
        if "|" not in line or line.lstrip().startswith(("+", "|")):  # leave tables alone
            continue
        parts = _LITERAL.split(line)
        parts[::2] = [_BARS.sub(r"\\|\1\\|", p) for p in parts[::2]]
        lines[i] = "".join(parts)


def setup(app):  # noqa: D103 - Sphinx hook
    _copy_notebooks()
    _cases_table()
    app.connect("autodoc-process-docstring", _escape_bars)
