"""The documentation builds from the project's own files with warnings as errors (make docs).

Sphinx + numpydoc (API from the docstrings) + myst-nb (the README tour, the notebooks executed
in quick mode, so their pages carry outputs and figures). Slow: it runs the notebooks. This
build is also the suite's one run of the notebooks (tests/test_notebooks.py checks their
sources): myst-nb stops the build on a cell's error (``nb_execution_raise_on_error``, so the
notebooks' own asserts fail it), and the executed copies it writes are checked below.
"""

import json
import os
import pathlib
import re
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted(p.stem for p in (ROOT / "notebooks").glob("*.ipynb"))


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    out = tmp_path_factory.mktemp("docs")
    cmd = [
        sys.executable,
        "-m",
        "sphinx",
        "-W",
        "--keep-going",
        "-b",
        "html",
        "-d",
        str(out / "doctrees"),
        str(ROOT / "docs"),
        str(out / "html"),
    ]
    run = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=1800)
    assert run.returncode == 0, run.stderr[-4000:]
    (out / "stderr.txt").write_text(run.stderr)
    return out / "html"


@pytest.mark.slow
def test_docs_build_says_only_what_needs_acting_on(site):
    # Issue 33: no kernel traceback (ZMQError), no kernel warning (TCP), no nbformat warning
    # per notebook: Sphinx's stderr carries warnings and errors only, and there are none.
    assert (site.parent / "stderr.txt").read_text().strip() == ""


@pytest.mark.slow
def test_formulas_render_offline(site):
    # MathJax is served by the site itself (from the docs extra), on every page, including the
    # notebook whose only TeX is python-control's transfer function in an output: no page
    # loads a script from the network.
    mathjax = site / "_static" / "mathjax" / "tex-svg.js"
    assert mathjax.stat().st_size > 1_000_000
    for page in [site / "api" / "control.html", *(site / "notebooks").glob("*.html")]:
        html = page.read_text()
        assert 'src="../_static/mathjax/tex-svg.js' in html, page.name
        assert not re.search(r"<script[^>]+src=\"(https?:)?//", html), page.name
    # python-control prints the transfer function's TeX in an HTML output, which MathJax is
    # told to typeset (class text_html).
    nb01 = (site / "notebooks" / "01_loop_analysis.html").read_text()
    assert '<div class="output text_html">' in nb01 and "\\dfrac{" in nb01
    assert re.search(r"processHtmlClass[^}]*text_html", nb01)


@pytest.mark.slow
@pytest.mark.parametrize("name", NOTEBOOKS)
def test_rendered_notebooks_show_no_warning(site, name):
    # Warnings meant for a notebook are explained in it; none is printed in a rendered page
    # (python-control's divide by zero, the LQG fit's, tqdm's "IProgress not found").
    page = (site / "notebooks" / f"{name}.html").read_text()
    assert not re.search(r"\w+Warning:", page), re.search(r".{200}\w+Warning:.{200}", page, re.S)
    assert "IProgress" not in page


@pytest.mark.slow
def test_docs_build_with_api_cases_and_notes(site):
    from aocontrol.study.cases import list_cases

    api = (site / "api" / "control.html").read_text()
    for name in ("aocontrol.synthesis.datadriven", "aocontrol.analysis.margins", "loop_plant"):
        assert name in api, name
    assert "aocontrol.study.report.comparison_report" in (site / "api" / "study.html").read_text()
    cases = (site / "cases.html").read_text()
    for name in list_cases():
        assert f'<code class="docutils literal notranslate"><span class="pre">{name}' in cases
    assert "stability_margins" in (site / "design_notes.html").read_text()
    assert "A five-minute tour" in (site / "tour.html").read_text()


@pytest.mark.slow
@pytest.mark.parametrize("name", NOTEBOOKS)
def test_notebook_pages_carry_their_outputs(site, name):
    page = (site / "notebooks" / f"{name}.html").read_text()
    assert "cell_output" in page  # executed: outputs rendered
    images = [p for p in (site / "_images").glob("*.png") if p.name in page]
    assert images, f"{name}: no figure in the rendered notebook"
    assert all(p.stat().st_size > 1000 for p in images)


def _stderr(nb: dict) -> str:
    return "".join(
        "".join(out.get("text", ""))
        for cell in nb["cells"]
        for out in cell.get("outputs", [])
        if out.get("output_type") == "stream" and out.get("name") == "stderr"
    )


@pytest.mark.slow
@pytest.mark.parametrize("name", NOTEBOOKS)
def test_notebooks_ran_top_to_bottom_in_the_build(site, name):
    # myst-nb writes each executed notebook to <out>/jupyter_execute/. Every code cell ran, in
    # order, in one kernel, without an error output; and no RuntimeWarning from aocontrol (the
    # suite's filterwarnings makes those errors in-process; the kernel only prints them).
    nb = json.loads((site.parent / "jupyter_execute" / "notebooks" / f"{name}.ipynb").read_text())
    code = [c for c in nb["cells"] if c["cell_type"] == "code"]
    assert code
    assert [c["execution_count"] for c in code] == list(range(1, len(code) + 1))
    errors = [o for c in code for o in c.get("outputs", []) if o.get("output_type") == "error"]
    assert errors == []
    ours = f"{ROOT / 'aocontrol'}{os.sep}"
    bad = [ln for ln in _stderr(nb).splitlines() if ln.startswith(ours) and "RuntimeWarning" in ln]
    assert bad == [], bad
