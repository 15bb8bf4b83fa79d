"""Sphinx configuration of the aocontrol documentation (``make docs``).

Sources: the API from the docstrings (autodoc + numpydoc), the README's tour and its notes on
python-control (included, one source), the science cases table (generated from the case files
at build time), and the six notebooks of ``notebooks/``, executed at build time in their quick
mode (``AOCONTROL_NOTEBOOK_QUICK=1``, a few minutes on 2 cores) by myst-nb, so the rendered
pages carry their outputs and figures. The notebooks are stored without outputs; a notebook
that fails to run fails the build. No pandoc, no network: MathJax is served from the site.
"""

from __future__ import annotations

import atexit
import json
import os
import pathlib
import re
import shutil
import subprocess
import sys
import tempfile

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))  # document this checkout, installed or not

# The kernel that executes the notebooks inherits this environment: quick mode, headless
# matplotlib, and this checkout on the path. Its sockets are Unix-domain ones (IPC), not TCP:
# no port to race for with another build or test run on the machine (over TCP a port picked
# free can be taken before the kernel binds it: "ZMQError: Address already in use"), and no
# warning that TCP is unencrypted.
os.environ["AOCONTROL_NOTEBOOK_QUICK"] = "1"
os.environ["PYTHONPATH"] = os.pathsep.join(
    [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])]
)

from jupyter_client import AsyncKernelManager  # noqa: E402
from nbclient import NotebookClient  # noqa: E402
from traitlets import default  # noqa: E402

import aocontrol  # noqa: E402

_KERNELS = tempfile.mkdtemp(prefix="aocontrol-docs-kernels-")  # the sockets' folder
atexit.register(shutil.rmtree, _KERNELS, ignore_errors=True)


class _IpcKernelManager(AsyncKernelManager):
    """nbclient's kernel manager on Unix-domain sockets, under an absolute prefix (the kernel
    runs in a temporary folder, the client in this process)."""

    @default("transport")
    def _transport_default(self) -> str:
        return "ipc"

    @default("ip")
    def _ip_default(self) -> str:
        return os.path.join(_KERNELS, "kernel")

    async def _async_launch_kernel(self, kernel_cmd, **kw):
        # The kernel process's own stderr (its shutdown's asyncio and joblib notes under load;
        # what a cell prints reaches the page through its messages, and a failing cell fails
        # the build) goes to a log beside the build, not to the build's output.
        kw.setdefault("stderr", _KERNEL_LOG[0] if _KERNEL_LOG else subprocess.DEVNULL)
        return await super()._async_launch_kernel(kernel_cmd, **kw)


_KERNEL_LOG: list = []  # the open log file, set when the builder starts (setup)


def _open_kernel_log(app) -> None:
    """``<outdir>/../kernels.log``: the notebook kernels' process stderr of this build."""
    path = pathlib.Path(app.outdir).parent / "kernels.log"
    path.parent.mkdir(parents=True, exist_ok=True)
    _KERNEL_LOG.append(open(path, "w"))  # open for the build's duration
    atexit.register(_KERNEL_LOG[0].close)


# myst-nb creates nbclient's NotebookClient without options: its default manager class is set.
NotebookClient._kernel_manager_class_default = lambda self: _IpcKernelManager

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
# MathJax renders the math nodes and, in notebook outputs, the TeX that python-control's
# transfer functions print in their HTML (class text_html); it is loaded on every page (setup).
myst_mathjax_classes = "tex2jax_process|mathjax_process|math|output_area|text_html"
myst_heading_anchors = 3

html_theme = "alabaster"
html_title = f"aocontrol {release}"
# MathJax 3 from the docs extra (django-static-mathjax ships its files), copied into the site by
# _mathjax(): the formulas render without a network. tex-svg.js draws glyphs as SVG paths from
# its own tables, so it needs no font files.
html_static_path = ["_generated/static"]
mathjax_path = "mathjax/tex-svg.js"
html_theme_options = {
    "description": "Adaptive-optics control toolbox",
    "fixed_sidebar": True,
    "page_width": "1200px",  # the cases table and the code cells need the room
    "body_max_width": "none",
}


def _copy_notebooks() -> None:
    """The notebooks of ``notebooks/`` into ``docs/notebooks/`` (Sphinx reads only docs/), each
    cell with an ``id`` (nbformat 4.5 requires one and warns for every notebook without)."""
    dst = HERE / "notebooks"
    dst.mkdir(exist_ok=True)
    for old in dst.glob("*.ipynb"):
        old.unlink()
    for nb in sorted((ROOT / "notebooks").glob("*.ipynb")):
        data = json.loads(nb.read_text(encoding="utf-8"))
        for i, cell in enumerate(data.get("cells", [])):
            cell.setdefault("id", f"cell-{i}")
        text = json.dumps(data, indent=1, ensure_ascii=False) + "\n"
        (dst / nb.name).write_text(text, encoding="utf-8")
        shutil.copystat(nb, dst / nb.name)


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


def _mathjax() -> None:
    """``docs/_generated/static/mathjax/tex-svg.js``: MathJax, from the installed package."""
    from importlib import resources

    try:
        src = resources.files("mathjax").joinpath("static", "mathjax", "es5", "tex-svg.js")
    except ModuleNotFoundError:
        raise RuntimeError(
            "MathJax is missing: install the docs extra (pip install -e '.[docs]'), which "
            "brings django-static-mathjax, so that the formulas render offline"
        ) from None
    dst = HERE / "_generated" / "static" / "mathjax" / "tex-svg.js"
    dst.parent.mkdir(parents=True, exist_ok=True)
    data = src.read_bytes()
    if not dst.exists() or dst.read_bytes() != data:
        dst.write_bytes(data)


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
    _mathjax()
    app.set_html_assets_policy("always")  # MathJax on pages whose only TeX is in an output
    app.connect("builder-inited", _open_kernel_log)
    app.connect("autodoc-process-docstring", _escape_bars)
